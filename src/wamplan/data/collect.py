"""Collect episodes into an :class:`EpisodeStore` with parallel worker processes.

The CPU simulator allows one env per process, so each worker (``wamplan.parallel``) owns one
``InsertionEnv`` and takes seeds from a queue. Every finished episode is written atomically by the
worker itself; the parent only counts. Killing the run (Ctrl-C or ``kill -9``) loses at most the episodes in flight; re-running the
same command skips the seeds already in the store.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import partial
from typing import Any, Iterator

import numpy as np

from wamplan.data.store import EpisodeData, EpisodeStore
from wamplan.envs.core import EnvConfig, InsertionEnv
from wamplan.envs.rollout import run_episode
from wamplan.parallel import imap_workers
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


class CollectWorker:
    """Holds one env and one policy; ``worker(seed)`` collects and stores that seed's episode."""

    def __init__(self, job: CollectJob):
        from wamplan.envs.commands import load_policy

        self.job = job
        self.env = InsertionEnv(job.env)
        self.policy = load_policy(job.policy_spec)
        self.store = EpisodeStore(job.store)

    def __call__(self, seed: int) -> dict[str, Any]:
        ep = collect_one(self.env, self.policy, seed, self.job.source, self.job.image_every, self.job.max_steps)
        self.store.write(ep)
        return dict(seed=seed, success=ep.success, outcome=ep.outcome, length=ep.length)


def run_collection(job: CollectJob, seeds: list[int], workers: int = 1) -> Iterator[dict[str, Any]]:
    """Collect ``seeds`` not yet in the store; yields one summary dict per finished episode."""
    store = EpisodeStore(job.store)
    todo = sorted(set(seeds) - store.finished_seeds(job.source))
    yield from imap_workers(partial(CollectWorker, job), todo, workers)


def throughput(start: float, n: int) -> float:
    """Episodes per minute since ``start``."""
    return 60.0 * n / max(time.perf_counter() - start, 1e-9)
