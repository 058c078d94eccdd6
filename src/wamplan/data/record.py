"""Record one episode of a policy into an :class:`EpisodeData`: every step's state (proprioception, stage
labels, the privileged poses the task has, the physics state and drive targets) and the task's cameras' views
every ``image_every`` steps and at the end.
The collection driver (:mod:`wamplan.data.collect`) and the counterfactual branches (:mod:`wamplan.data.branch`)
both record through it."""

from __future__ import annotations

import numpy as np

from wamplan.data.store import POSES, EpisodeData
from wamplan.envs.core import TaskEnv
from wamplan.policies.base import Policy
from wamplan.policies.rollout import run_episode
from wamplan.provenance import provenance

STATE_KEYS = ("proprio", "stages", *POSES, "sim_state", "drive_targets")  # per step, (T+1, ...)


def record_state(rec: dict[str, list], env: TaskEnv, obs) -> None:
    """Append the per-step state arrays of ``obs`` (and the env's physics state) to ``rec``'s lists; a pose the
    task's privileged state lacks is appended as None."""
    rec["proprio"].append(obs.proprio)
    rec["stages"].append(obs.state["stages"])
    for k in POSES:
        rec[k].append(obs.state.get(k))
    rec["sim_state"].append(env.sim_state())
    rec["drive_targets"].append(env.drive_targets())


def stack_state(rec: dict[str, list]) -> dict[str, np.ndarray | None]:
    """The recorded lists as arrays, (T+1, ...) each; None for a pose the task never had."""
    return {k: None if v and v[0] is None else np.stack(v) for k, v in rec.items()}


def collect_one(env: TaskEnv, policy: Policy, seed: int, source: str, image_every: int,
                max_steps: int | None = None, on_step=None) -> EpisodeData:
    """Run one episode, recording states every step and the task's views every ``image_every`` steps and at the end.
    ``on_step(env, obs, action)`` is called after each recorded observation (e.g. to take snapshots)."""
    cameras = env.task.cameras
    rec: dict[str, list] = {k: [] for k in (*STATE_KEYS, "image_steps")}
    actions: list[np.ndarray] = []
    frames: dict[str, list] = {c: [] for c in cameras}

    def on_obs(e: TaskEnv, obs, action) -> None:
        if action is not None:
            actions.append(action)
        record_state(rec, e, obs)
        if obs.images is not None and obs.step % image_every == 0:
            rec["image_steps"].append(obs.step)
            for c in cameras:
                frames[c].append(obs.images[c])
        if on_step is not None:
            on_step(e, obs, action)

    r = run_episode(env, policy, seed, images_at=lambda t: t % image_every == 0, on_obs=on_obs, max_steps=max_steps)
    if not rec["image_steps"] or rec["image_steps"][-1] != r.length:  # always keep the final frame
        views = env.render()
        rec["image_steps"].append(r.length)
        for c in cameras:
            frames[c].append(views[c])
    arrays = stack_state(rec)
    acts = np.stack(actions) if actions else np.zeros((0, env.task.action_dim), np.float32)  # (T, A)
    return EpisodeData(seed=seed, source=source, success=r.success, outcome=r.outcome, actions=acts,
                       proprio=arrays["proprio"], stages=arrays["stages"], cube_pose=arrays["cube_pose"],
                       tcp_pose=arrays["tcp_pose"], target_pose=arrays["target_pose"], sim_state=arrays["sim_state"],
                       drive_targets=arrays["drive_targets"], image_steps=arrays["image_steps"].astype(np.int32),
                       images={c: np.stack(frames[c]) for c in cameras}, reached=r.reached,
                       policy=policy.config_dict(),
                       provenance=provenance(max_steps=max_steps or env.max_episode_steps,
                                             wall_time_s=round(r.wall_time, 3)))
