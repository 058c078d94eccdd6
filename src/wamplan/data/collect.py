"""Collect episodes into an :class:`EpisodeStore` with parallel worker processes or Ray actors.

The CPU simulator allows one env per process, so each worker (``wamplan.parallel``) owns one
``TaskEnv`` and takes seeds from a queue. Every finished episode is written atomically: by a
worker process itself (the parent only counts), or, on Ray, by the driver from the episode the actor
returns (the store need not be reachable from the cluster's nodes, and an item retried after its
actor died still yields one episode). Killing the run (Ctrl-C or ``kill -9``) loses at most the
episodes in flight; re-running the same command skips the seeds already in the store.

A store holds one task's episodes: the env's (``EnvConfig.task``), recorded when the store is created; collecting
into a store of another task is refused. Every policy is loaded for the worker's task (``task=env.task``).
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

from wamplan.config import one_checkpoint
from wamplan.data.record import collect_one
from wamplan.data.store import MANIFEST, EpisodeData, EpisodeStore
from wamplan.envs.config import EnvConfig
from wamplan.envs.core import TaskEnv
from wamplan.errors import UserError, require_paths, require_positive, require_seeds
from wamplan.locks import dir_lock
from wamplan.parallel import Backend, imap_workers
from wamplan.policies.base import Policy, make_policy
from wamplan.provenance import provenance


@dataclass(frozen=True)
class CollectJob:
    """What a worker needs to rebuild its env and policy in a fresh process (all picklable)."""

    store: str
    source: str  # expert | noisy-expert | pink | policy:<name> | another tag of a registered policy's episodes
    policy_spec: str  # a registered policy name or a WAM checkpoint directory
    env: EnvConfig
    image_every: int
    max_steps: int | None = None
    loader: Callable[..., Policy] = make_policy  # (policy_spec, task=, **policy_kwargs) -> Policy; picklable
    branch: Any = None  # a wamplan.data.branch.BranchSpec: also store counterfactual branches of each episode
    policy_kwargs: dict[str, Any] = field(default_factory=dict)  # loader(policy_spec, **these)


class CollectWorker:
    """Holds one env and one policy; ``worker(seed)`` collects and stores that seed's episode, or with
    ``write=False`` returns it under ``"episode"`` for the caller to store."""

    def __init__(self, job: CollectJob, write: bool = True):
        self.job = job
        self.env = TaskEnv(job.env)
        self.policy = job.loader(job.policy_spec, task=self.env.task, **job.policy_kwargs)
        self.store = EpisodeStore(job.store) if write else None

    def __call__(self, seed: int) -> dict[str, Any]:
        branches: list[EpisodeData] = []
        if self.job.branch is not None:
            from wamplan.data.branch import collect_branched

            ep, branches = collect_branched(self.env, self.policy, seed, self.job.source, self.job.image_every,
                                            self.job.branch, self.job.max_steps)
        else:
            ep = collect_one(self.env, self.policy, seed, self.job.source, self.job.image_every, self.job.max_steps)
        summary: dict[str, Any] = dict(seed=seed, success=ep.success, outcome=ep.outcome, length=ep.length,
                                       branches=len(branches))
        if self.store is None:
            return dict(summary, episode=ep, branch_episodes=branches)
        for b in branches:  # the parent last: its presence says its branches are complete
            self.store.write(b)
        self.store.write(ep)
        return summary


def run_collection(job: CollectJob, seeds: list[int], workers: int = 1,
                   backend: Backend = Backend()) -> Iterator[dict[str, Any]]:
    """Collect ``seeds`` not yet in the store; yields one summary dict per finished episode."""
    backend.check()
    store = EpisodeStore(job.store)
    todo = sorted(set(seeds) - store.finished_seeds(job.source))
    if job.branch is not None:
        from wamplan.data.branch import drop_unfinished_branches

        drop_unfinished_branches(store, job.source)
    if backend.kind == "processes":
        yield from imap_workers(partial(CollectWorker, job), todo, workers)
        return
    for rec in imap_workers(partial(CollectWorker, job, False), todo, workers, backend):
        for b in rec.pop("branch_episodes"):  # here, once per seed, however often the actor was retried
            store.write(b)
        store.write(rec.pop("episode"))
        yield rec


def check_done(store: EpisodeStore, paths: Sequence[Path], progress: bool = True) -> None:
    """Refuse to resume over a damaged episode file: every byte of each of ``paths`` is read through its
    checksums; one :class:`StoreError` line names the first damaged file and the fix (delete it, re-run)."""
    from wamplan.data.store import RECOLLECT, StoreError, verify_episode
    from wamplan.progress import progress_bar

    for path in progress_bar(paths, desc="check collected", unit="ep", disable=not progress or len(paths) < 20):
        problem, _ = verify_episode(path)  # the header, attributes and every chunk
        if problem is not None:
            raise StoreError(f"episode file {path} is damaged ({problem}); {RECOLLECT}")


def throughput(start: float, n: int) -> float:
    """Episodes per minute since ``start``."""
    return 60.0 * n / max(time.perf_counter() - start, 1e-9)


def collect(source: str, episodes: int, out: str | Path, *, seed_start: int = 0, workers: int = 1,
            policy: str | None = None, image_every: int = 4, max_steps: int | None = None,
            env: EnvConfig | None = None, progress: bool = True, log=print,
            loader: Callable[..., Policy] = make_policy, backend: Backend = Backend(),
            branch: Any = None, policy_kwargs: dict[str, Any] | None = None,
            plan_with: str = "", seeds: Sequence[int] | None = None,
            policy_name: str | None = None) -> dict[str, Any]:
    """Collect seeds ``seed_start .. seed_start + episodes - 1`` of ``source`` (expert, noisy-expert, pink,
    or policy with ``policy`` a WAM checkpoint) into the store ``out``, skipping the seeds it holds.
    ``seeds`` (``episodes`` of them; may be empty) replaces that range. ``env`` (default ``EnvConfig()``)
    names the task; a new store records it, an existing one must hold the same task's episodes.
    ``policy_name``: the registered policy that acts when ``source`` only tags its episodes (e.g. source
    ``demo`` acted by ``demo-replay``); by default the source is the policy's name.
    ``loader(spec, task=env's task, **policy_kwargs)`` builds the policy from its name or checkpoint in each
    worker: the registered policies by default; pass ``wamplan.evaluation.build.load_policy`` to run WAM
    checkpoints (a layer above data).
    ``backend``: worker processes here, or Ray actors (see ``wamplan.parallel``). ``branch`` (a
    ``wamplan.data.branch.BranchSpec``, policy sources only) also stores counterfactual branches per episode.
    ``policy_kwargs`` go to the policy's constructor (e.g. ``config=ExpertConfig(...)`` for the expert).
    ``plan_with`` (a world model checkpoint; policy sources, with ``load_policy`` as the loader) plans every
    chunk of the WAM in that model, so the episodes (and branches) follow the planner's own trajectories; their
    source is ``policy:<wam>+plan:<world model>``, apart from the open-loop ``policy:<wam>`` episodes.
    Returns a summary (collected, skipped, seconds, episodes_per_min, outcomes)."""
    from wamplan.progress import progress_bar

    backend.check()
    require_positive(("--episodes", episodes if seeds is None else None), ("--workers", workers),
                     ("--image-every", image_every))
    if seeds is None:
        require_seeds(seed_start, episodes)
        seeds = list(range(seed_start, seed_start + episodes))
    else:
        seeds = list(dict.fromkeys(int(s) for s in seeds))
        if len(seeds) != episodes:
            raise ValueError(f"episodes={episodes} but {len(seeds)} distinct seeds were given")
        for s in (min(seeds), max(seeds)) if seeds else ():
            require_seeds(s, flag="seeds")
    if source == "policy":
        if not policy:
            raise UserError("--source policy needs --policy CKPT (a WAM checkpoint directory)")
        if policy_name:
            raise UserError(f"--source policy runs the WAM checkpoint --policy, not the registered '{policy_name}'")
        spec, tag = policy, f"policy:{Path(policy).resolve().name}"
        if plan_with:
            if loader is make_policy:
                raise UserError("plan_with builds a planned WAM, which the registered policies' loader cannot: pass "
                                "loader=wamplan.evaluation.build.load_policy")
            model = one_checkpoint(plan_with, "--plan-with")
            require_paths([model], "--plan-with", "pass a world model checkpoint (e.g. from `wamplan wm train`)")
            tag += "+plan:" + Path(model).resolve().name
            policy_kwargs = dict(policy_kwargs or {}, plan_with=plan_with)
    elif plan_with:
        raise UserError(f"--plan-with needs --source policy (it plans a WAM's chunks), got --source {source}")
    else:
        if policy:
            raise UserError(f"--policy is only for --source policy (got --source {source})")
        spec, tag = policy_name or source, source
    if branch is not None and source != "policy":
        raise UserError(f"--branches needs --source policy (branches perturb a WAM's chunks), got --source {source}")
    env = env or EnvConfig()
    job = CollectJob(store=str(out), source=tag, policy_spec=spec, env=env, image_every=image_every,
                     max_steps=max_steps, loader=loader, branch=branch,
                     policy_kwargs=dict(policy_kwargs or {}))
    # a damaged or foreign checkpoint, a policy for another task: one line now, not in a worker (and, for a new
    # store, before anything is written)
    checked = False
    if seeds and not (Path(out) / MANIFEST).is_file():
        loader(spec, task=env.spec, **job.policy_kwargs)
        checked = True
    store = EpisodeStore(out, create=True, env=env.task_kwargs(), image_every=image_every, provenance=provenance(),
                         task=env.spec)
    with dir_lock(store.root, "collected into"):  # one collector a store (workers write, the parent holds it)
        if (n := store.clean_partial()):
            log(f"removed {n} partial episode file(s) left by an interrupted run")
        store.check_source(tag)
        have = store.finished_seeds(tag) & set(seeds)
        check_done(store, [store.episode_path(tag, seed) for seed in sorted(have)], progress)
        if have:
            log(f"resuming: {len(have)} of {len(seeds)} episodes already in {out}")
        if len(have) < len(seeds) and not checked:
            loader(spec, task=env.spec, **job.policy_kwargs)
        counts: Counter = Counter()
        start, n = time.perf_counter(), 0
        bar = progress_bar(total=len(seeds), initial=len(have), desc=f"collect {tag}", unit="ep",
                           disable=not progress)
        for rec in run_collection(job, seeds, workers=workers, backend=backend):
            n += 1
            counts[rec["outcome"]] += 1
            bar.update(1)
            bar.set_postfix(ep_per_min=f"{throughput(start, n):.1f}", success=f"{counts['success']}/{n}")
        bar.close()
    return dict(source=tag, collected=n, skipped=len(have), seconds=round(time.perf_counter() - start, 1),
                episodes_per_min=round(throughput(start, n), 2) if n else None, outcomes=dict(counts))
