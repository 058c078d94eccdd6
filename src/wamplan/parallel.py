"""Fan work items out to worker processes, each holding expensive state (a simulator, models).

The CPU simulator allows one env per process, so collection and evaluation build one "worker" per
process with ``make_worker()`` (a picklable callable, e.g. a class and its config) and feed it items.
Results come back in completion order. An orphaned worker (its parent was killed) stops after its
current item. The item -> result mapping is all a cluster back-end would need to replace this.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue
from typing import Callable, Iterator, TypeVar

T = TypeVar("T")
R = TypeVar("R")


def _serve(make_worker: Callable[[], Callable[[T], R]], items: "mp.Queue", results: "mp.Queue", parent: int,
           threads: int) -> None:
    import torch

    torch.set_num_threads(threads)  # oversubscribed cores make torch's thread pools collapse (~50x slower)
    work = make_worker()
    while os.getppid() == parent:
        item = items.get()
        if item is None:
            break
        results.put(work(item))


def imap_workers(make_worker: Callable[[], Callable[[T], R]], items: list[T], workers: int = 1) -> Iterator[R]:
    """Yield ``work(item)`` for every item, computed by ``workers`` processes (inline when 1)."""
    if not items:
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
    threads = max(1, (os.cpu_count() or 1) // n)
    procs = [ctx.Process(target=_serve, args=(make_worker, item_q, res_q, os.getpid(), threads), daemon=True)
             for _ in range(n)]
    for p in procs:
        p.start()
    try:
        done = 0
        while done < len(items):
            try:
                yield res_q.get(timeout=1.0)
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
