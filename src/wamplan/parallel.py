"""Fan work items out to workers, each holding expensive state (a simulator, models), on this machine
or on a Ray cluster.

The CPU simulator allows one env per process, so collection and evaluation build one "worker" per
process with ``make_worker()`` (a picklable callable, e.g. a class and its config) and feed it items;
results come back in completion order, and the caller records each as it arrives (so a killed run
keeps every result it received and a re-run skips them). Two back-ends run the same item -> result
mapping:

- ``processes`` (default): spawned processes on this machine fed from a queue. An orphaned worker
  (its parent was killed) stops after its current item.
- ``ray``: one Ray actor per worker, each holding its ``make_worker()`` state like a process worker
  does, fed one item at a time by the driver (an actor pool: a free actor takes the next item).
  Actors, not stateless tasks, because the state costs seconds to build (an env, checkpoints) and an
  episode only seconds to minutes to run. An actor that dies mid-item (its process or node killed)
  is restarted and the item retried (``max_restarts`` / ``max_task_retries``); the driver gets one
  result per item whatever the attempts, so nothing is recorded twice. Actors are owned by the
  driver: a killed driver takes them with it, and its re-run resumes from the recorded results.
  Ray is optional (``pip install wamplan[ray]``); ``address`` "" starts a local cluster for the run,
  "auto" or host:port joins an existing one (``ray start --head``); an already connected driver
  (``ray.init`` called before, e.g. by a test) is used as it is.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue
from dataclasses import dataclass
from typing import Any, Callable, Iterator, TypeVar

from wamplan.config import require

T = TypeVar("T")
R = TypeVar("R")
BACKENDS = ("processes", "ray")
RAY_MISSING = "--ray needs Ray, which is not installed; install it with: pip install 'wamplan[ray]'"


@dataclass(frozen=True)
class Backend:
    """Where workers run: ``processes`` on this machine, or ``ray`` actors on a cluster."""

    kind: str = "processes"
    address: str = ""  # ray: "" starts a local cluster for the run; "auto" or host:port joins one
    retries: int = 3  # ray: restarts of a dead actor, and retries of the item it was running

    def __post_init__(self):
        require(self.kind in BACKENDS, f"backend must be one of {BACKENDS}, got '{self.kind}'")
        require(self.retries >= 0, f"retries must be >= 0, got {self.retries}")
        require(self.kind == "ray" or not self.address, "an address is only for the ray backend; pass --ray ADDRESS")

    def check(self) -> None:
        """Fail now, in one line, where the back-end cannot run (Ray not installed)."""
        if self.kind == "ray":
            import_ray()

    @classmethod
    def from_option(cls, ray: str | None) -> "Backend":
        """From ``--ray [ADDRESS]`` (None: not given; "": given without an address)."""
        return cls() if ray is None else cls("ray", ray)


def add_backend_argument(p) -> None:
    """``--ray [ADDRESS]`` on an argparse parser (dest ``ray``; see :meth:`Backend.from_option`)."""
    p.add_argument("--ray", nargs="?", const="", default=None, metavar="ADDRESS",
                   help="run the workers as Ray actors: on a local cluster started for the run, or on the cluster "
                        "at ADDRESS ('auto' or host:port, see `ray start --head`); --workers actors of 1 CPU each "
                        "(needs pip install 'wamplan[ray]')")


@dataclass(frozen=True)
class _Refused:
    """A worker process's :class:`~wamplan.errors.UserError` (a bad checkpoint, a damaged file), sent to the
    driver, which raises it: one line for people, as in a run without workers, not a worker's traceback."""

    error: Exception


def _serve(make_worker: Callable[[], Callable[[T], R]], items: "mp.Queue", results: "mp.Queue", parent: int,
           threads: int) -> None:
    import torch

    from wamplan.errors import UserError

    torch.set_num_threads(threads)  # oversubscribed cores make torch's thread pools collapse (~50x slower)
    try:
        work = make_worker()
        while os.getppid() == parent:
            item = items.get()
            if item is None:
                break
            results.put(work(item))
    except UserError as e:
        results.put(_Refused(e))


def threads_per_worker(workers: int) -> int:
    """torch threads for each of ``workers`` processes: the cores split evenly, and never more than the user's
    ``OMP_NUM_THREADS`` (so several jobs started side by side with ``OMP_NUM_THREADS=1`` stay one thread each)."""
    threads = max(1, (os.cpu_count() or 1) // max(1, workers))
    cap = os.environ.get("OMP_NUM_THREADS", "").strip()
    return min(threads, int(cap)) if cap.isdigit() and int(cap) > 0 else threads


def imap_workers(make_worker: Callable[[], Callable[[T], R]], items: list[T], workers: int = 1,
                 backend: Backend = Backend()) -> Iterator[R]:
    """Yield ``work(item)`` for every item, computed by ``workers`` processes (inline when 1) or Ray actors."""
    if not items:
        return
    if backend.kind == "ray":
        yield from _imap_ray(make_worker, items, workers, backend)
        return
    if workers <= 1:
        work = make_worker()
        for item in items:
            yield work(item)
        return
    ctx = mp.get_context("spawn")
    item_q, res_q = ctx.Queue(), ctx.Queue()
    n = min(workers, len(items))
    for it in items:
        item_q.put(it)
    for _ in range(n):
        item_q.put(None)
    threads = threads_per_worker(n)
    procs = [ctx.Process(target=_serve, args=(make_worker, item_q, res_q, os.getpid(), threads), daemon=True)
             for _ in range(n)]
    for p in procs:
        p.start()
    try:
        done = 0
        while done < len(items):
            try:
                result = res_q.get(timeout=1.0)
                if isinstance(result, _Refused):
                    raise result.error
                yield result
                done += 1
            except queue.Empty:
                dead = [p for p in procs if not p.is_alive() and p.exitcode not in (0, None)]
                if dead:
                    raise RuntimeError(f"a worker process died (exit code {dead[0].exitcode}); finished results are "
                                       f"kept, re-run the same command to resume")
        for p in procs:
            p.join()
    finally:
        for p in procs:
            if p.is_alive():
                p.terminate()


def import_ray():
    """The ``ray`` module, or a one-line :class:`UserError` that says how to install it."""
    from wamplan.errors import UserError

    try:
        import ray
    except ImportError:
        raise UserError(RAY_MISSING) from None
    return ray


class _Hosted:
    """A Ray actor's body: builds the worker once, then runs the items it is given."""

    def __init__(self, make_worker: Callable[[], Callable[[Any], Any]]):
        import torch

        torch.set_num_threads(1)  # one CPU per actor (num_cpus=1)
        self.work, self.error = None, None
        try:
            self.work = make_worker()
        except Exception as e:  # raised by run(): a task's error reaches the driver as itself, an actor's would not
            self.error = e

    def run(self, item: Any) -> Any:
        if self.error is not None:
            raise self.error
        return self.work(item)


def _imap_ray(make_worker: Callable[[], Callable[[T], R]], items: list[T], workers: int,
              backend: Backend) -> Iterator[R]:
    from wamplan.errors import UserError

    ray = import_ray()
    started = not ray.is_initialized()
    if started:
        local = dict(num_cpus=max(workers, 1), include_dashboard=False) if not backend.address else {}
        try:
            ray.init(address=backend.address or "local", log_to_driver=False, **local)
        except ConnectionError as e:
            raise UserError(f"cannot join the Ray cluster at '{backend.address}' ({e}); check the address "
                            f"(`ray status` on its head node); where the cluster uses token authentication (Ray's "
                            f"default) set RAY_AUTH_MODE=token with its token (~/.ray/auth_token or RAY_AUTH_TOKEN)"
                            ) from None
    actor_cls = ray.remote(num_cpus=1, max_restarts=backend.retries, max_task_retries=backend.retries)(_Hosted)
    actors = [actor_cls.remote(make_worker) for _ in range(min(max(workers, 1), len(items)))]
    todo, end = iter(items), object()
    pending: dict[Any, Any] = {}  # ObjectRef -> the actor running it

    def submit(actor) -> None:
        item = next(todo, end)
        if item is not end:
            pending[actor.run.remote(item)] = actor

    try:
        for a in actors:
            submit(a)
        while pending:
            [ref], _ = ray.wait(list(pending), num_returns=1)
            actor = pending.pop(ref)
            try:
                result = ray.get(ref)
            except ray.exceptions.RayTaskError as e:  # the worker raised: not retried, as with processes
                if isinstance(e.cause, UserError):
                    raise e.cause from None  # one line for people (e.g. a missing checkpoint on a node)
                raise
            except ray.exceptions.RayActorError as e:
                raise RuntimeError(f"a Ray worker died and its {backend.retries} restart(s) are used up "
                                   f"({type(e).__name__}); finished results are kept, re-run the same command to "
                                   f"resume") from None
            submit(actor)  # keep the actor busy while the caller records the result
            yield result
    finally:
        for a in actors:
            ray.kill(a)
        if started:
            ray.shutdown()
