"""Record one episode of a policy into an :class:`EpisodeData`: every step's state (proprioception, stage
labels, poses, the physics state and drive targets) and the views every ``image_every`` steps and at the end.
The collection driver (:mod:`wamplan.data.collect`) and the counterfactual branches (:mod:`wamplan.data.branch`)
both record through it."""

from __future__ import annotations

import numpy as np

from wamplan.data.store import EpisodeData
from wamplan.envs.contract import CAMERAS
from wamplan.envs.core import InsertionEnv
from wamplan.policies.base import Policy
from wamplan.policies.rollout import run_episode
from wamplan.provenance import provenance

STATE_KEYS = ("proprio", "stages", "cube_pose", "tcp_pose", "sim_state", "drive_targets")  # per step, (T+1, ...)


def record_state(rec: dict[str, list], env: InsertionEnv, obs) -> None:
    """Append the per-step state arrays of ``obs`` (and the env's physics state) to ``rec``'s lists."""
    rec["proprio"].append(obs.proprio)
    rec["stages"].append(obs.state["stages"])
    rec["cube_pose"].append(obs.state["cube_pose"])
    rec["tcp_pose"].append(obs.state["tcp_pose"])
    rec["sim_state"].append(env.sim_state())
    rec["drive_targets"].append(env.drive_targets())


def collect_one(env: InsertionEnv, policy: Policy, seed: int, source: str, image_every: int,
                max_steps: int | None = None, on_step=None) -> EpisodeData:
    """Run one episode, recording states every step and the three views every ``image_every`` steps and at the end.
    ``on_step(env, obs, action)`` is called after each recorded observation (e.g. to take snapshots)."""
    rec: dict[str, list] = {k: [] for k in (*STATE_KEYS, "actions", "image_steps")}
    frames: dict[str, list] = {c: [] for c in CAMERAS}

    def on_obs(e: InsertionEnv, obs, action) -> None:
        if action is not None:
            rec["actions"].append(action)
        record_state(rec, e, obs)
        if obs.images is not None and obs.step % image_every == 0:
            rec["image_steps"].append(obs.step)
            for c in CAMERAS:
                frames[c].append(obs.images[c])
        if on_step is not None:
            on_step(e, obs, action)

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
