"""Collect episodes into an :class:`EpisodeStore` with parallel worker processes.

The CPU simulator allows one env per process, so each worker owns one ``InsertionEnv`` and pulls seeds
from a queue. Every finished episode is written atomically by the worker itself; the parent only
counts. Killing the run (Ctrl-C or ``kill -9``) loses at most the episodes in flight; re-running the
same command skips the seeds already in the store.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue
import time
from dataclasses import dataclass
from typing import Any, Iterator

import numpy as np

from wamplan.data.store import EpisodeData, EpisodeStore
from wamplan.envs.core import EnvConfig, InsertionEnv
from wamplan.envs.rollout import run_episode
from wamplan.policies.base import CAMERAS, Policy
from wamplan.provenance import provenance


@dataclass(frozen=True)
class CollectJob:
    """What a worker needs to rebuild its env and policy in a fresh process (all picklable)."""

    store: str
    source: str  # expert | noisy-expert | pink | policy:<name>
    policy_spec: str  # a registered policy name or a WAM checkpoint directory
    env: EnvConfig
    image_every: int
    max_steps: int | None = None


def collect_one(env: InsertionEnv, policy: Policy, seed: int, source: str, image_every: int,
                max_steps: int | None = None) -> EpisodeData:
    """Run one episode, recording states every step and the three views every ``image_every`` steps and at the end."""
    rec: dict[str, list] = {k: [] for k in ("proprio", "stages", "cube_pose", "tcp_pose", "sim_state", "drive_targets",
                                            "actions", "image_steps")}
    frames: dict[str, list] = {c: [] for c in CAMERAS}

    def on_obs(e: InsertionEnv, obs, action) -> None:
        if action is not None:
            rec["actions"].append(action)
        rec["proprio"].append(obs.proprio)
        rec["stages"].append(obs.state["stages"])
        rec["cube_pose"].append(obs.state["cube_pose"])
        rec["tcp_pose"].append(obs.state["tcp_pose"])
        rec["sim_state"].append(e.sim_state())
        rec["drive_targets"].append(e.drive_targets())
        if obs.images is not None and obs.step % image_every == 0:
            rec["image_steps"].append(obs.step)
            for c in CAMERAS:
                frames[c].append(obs.images[c])

    r = run_episode(env, policy, seed, images_at=lambda t: t % image_every == 0, on_obs=on_obs, max_steps=max_steps)
    if not rec["image_steps"] or rec["image_steps"][-1] != r.length:  # always keep the final frame
        views = env.render()
        rec["image_steps"].append(r.length)
        for c in CAMERAS:
            frames[c].append(views[c])
    arrays = {k: np.stack(v) if v else np.zeros((0, 5), np.float32) for k, v in rec.items()}
    return EpisodeData(seed=seed, source=source, success=r.success, outcome=r.outcome, actions=arrays["actions"],
                       proprio=arrays["proprio"], stages=arrays["stages"], cube_pose=arrays["cube_pose"],
                       tcp_pose=arrays["tcp_pose"], sim_state=arrays["sim_state"],
                       drive_targets=arrays["drive_targets"], image_steps=arrays["image_steps"].astype(np.int32),
                       images={c: np.stack(frames[c]) for c in CAMERAS}, reached=r.reached,
                       policy=policy.config_dict(),
                       provenance=provenance(max_steps=max_steps or env.config.max_episode_steps,
                                             wall_time_s=round(r.wall_time, 3)))


def _make_policy(spec: str) -> Policy:
    from wamplan.envs.commands import load_policy

    return load_policy(spec)


def _worker(job: CollectJob, seeds: "mp.Queue[int | None]", results: "mp.Queue[dict]", parent: int) -> None:
    env = InsertionEnv(job.env)
    policy = _make_policy(job.policy_spec)
    store = EpisodeStore(job.store)
    while os.getppid() == parent:  # an orphan (parent killed) stops instead of collecting on
        seed = seeds.get()
        if seed is None:
            break
        ep = collect_one(env, policy, seed, job.source, job.image_every, job.max_steps)
        store.write(ep)
        results.put(dict(seed=seed, success=ep.success, outcome=ep.outcome, length=ep.length))
    env.close()


def run_collection(job: CollectJob, seeds: list[int], workers: int = 1) -> Iterator[dict[str, Any]]:
    """Collect ``seeds`` not yet in the store; yields one summary dict per finished episode."""
    store = EpisodeStore(job.store)
    todo = sorted(set(seeds) - store.finished_seeds(job.source))
    if not todo:
        return
    if workers <= 1:
        env, policy = InsertionEnv(job.env), _make_policy(job.policy_spec)
        try:
            for seed in todo:
                ep = collect_one(env, policy, seed, job.source, job.image_every, job.max_steps)
                store.write(ep)
                yield dict(seed=seed, success=ep.success, outcome=ep.outcome, length=ep.length)
        finally:
            env.close()
        return
    ctx = mp.get_context("spawn")
    seed_q, res_q = ctx.Queue(), ctx.Queue()
    for s in todo:
        seed_q.put(s)
    n = min(workers, len(todo))
    for _ in range(n):
        seed_q.put(None)
    procs = [ctx.Process(target=_worker, args=(job, seed_q, res_q, os.getpid()), daemon=True) for _ in range(n)]
    for p in procs:
        p.start()
    try:
        done = 0
        while done < len(todo):
            try:
                yield res_q.get(timeout=1.0)
                done += 1
            except queue.Empty:
                dead = [p for p in procs if not p.is_alive() and p.exitcode not in (0, None)]
                if dead:
                    raise RuntimeError(f"a collection worker died (exit code {dead[0].exitcode}); finished episodes "
                                       f"are kept, re-run the same command to resume")
        for p in procs:
            p.join()
    finally:
        for p in procs:
            if p.is_alive():
                p.terminate()


def throughput(start: float, n: int) -> float:
    """Episodes per minute since ``start``."""
    return 60.0 * n / max(time.perf_counter() - start, 1e-9)

