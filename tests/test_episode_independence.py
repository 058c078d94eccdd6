"""An episode's record depends only on its seed and its policy, not on what its worker ran before it.

Before ``TaskEnv.reset`` rebuilt the scene once physics had stepped, PhysX carried hidden state across
resets: the noisy expert's seed 3 drifted from step 51 on when run after seed 7, and an evaluation record's
first trace row said ``grasped`` (a contact left from the previous episode's grasp, 240 mm away).
"""

from __future__ import annotations

import numpy as np

from wamplan.envs.config import EnvConfig
from wamplan.envs.core import TaskEnv
from wamplan.evaluation.trace import CubeTrace
from wamplan.policies import make_policy
from wamplan.policies.rollout import run_episode


def _record(env: TaskEnv, seed: int) -> dict:
    """What an evaluation record keeps of an episode (outcome, length, stages, the cube's trace), plus every
    step's proprio and cube pose."""
    trace, rows = CubeTrace(every=4), []

    def hook(e, obs, action):
        trace(e, obs, action)
        rows.append(np.concatenate([obs.proprio, obs.state["cube_pose"]]))  # (17,)

    r = run_episode(env, make_policy("noisy-expert"), seed, on_obs=hook)
    return dict(r.summary(), wall_time=None, reached=r.reached, **trace.summary(), states=np.stack(rows).tolist())


def test_a_seed_run_first_and_third_in_a_process_gives_identical_records():
    env = TaskEnv(EnvConfig(camera_size=64))  # a fresh process's env: seed 3 runs first, as in a new worker
    try:
        first = _record(env, 3)
        _record(env, 7)  # grasps, lifts and seats the cube: contacts, drive targets, solver state to carry over
        third = _record(env, 3)
    finally:
        env.close()
    assert first["trace"][0]["grasped"] is False
    assert first["length"] == third["length"] and first["outcome"] == third["outcome"]
    assert first == third
