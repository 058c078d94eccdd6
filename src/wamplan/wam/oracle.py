"""The expert oracle WAM: the scripted expert simulated forward in the live environment.

At each query it snapshots the env, rolls a copy of the expert H steps forward from the (restored)
current state, records the H actions, renders the true views at t + H, and puts the env back. It is
the upper bound for a WAM (perfect actions, perfect predicted images) and a debugging aid for the
planner: its image targets are exactly reachable.

The expert is a state machine (approach, descend, close, ...). Its phase must fit the state the query
starts from, whoever drove the robot there: before simulating, the oracle re-synchronises its expert to
the current state (``ExpertPolicy.sync_to``: the phase that fits the grasp flag, the gripper and the poses;
a phase that already fits keeps its counters). So in conditions 2-4, where a planner or the WAM executes
chunks other than the expert's, the target and the seed are what the expert would do from the current
state, never a phase left over from a chunk that was not executed. Executed open loop (``WAMPolicy``),
the executed trajectory is the simulated one: with the "restore before simulating, restore again before
executing" rule the two are bit-identical (PhysX keeps hidden state, so a rollout from a restored state
differs slightly from one that never was).

It needs the live env, so it cannot be loaded from a checkpoint: ``make_wam("expert-oracle", env=env)``. Its
task, action size and cameras are the env's (``env.task``); the task must be one the scripted expert solves
(``TaskSpec.expert == "expert"``: cube-insertion).
"""

from __future__ import annotations

import copy
import time
from typing import Any

import numpy as np

from wamplan.envs.spec import Observation
from wamplan.policies.expert import ExpertPolicy
from wamplan.wam.base import WAM, WAMError, WAMOutput, register_wam


@register_wam("expert-oracle")
class ExpertOracleWAM(WAM):
    """``ExpertOracleWAM(env, chunk=16, image_size=None)``: the expert's next ``chunk`` actions and the true
    views after them. ``image_size`` resizes the rendered views (None keeps the env's camera size); ``cameras``
    (default: the env's task's) are the views it renders."""

    def __init__(self, env: Any, chunk: int = 16, image_size: int | None = None,
                 expert: ExpertPolicy | None = None, cameras: tuple[str, ...] | None = None):
        if not (hasattr(env, "snapshot") and hasattr(env, "restore") and hasattr(env, "render")
                and hasattr(env, "task")):
            raise WAMError(f"the expert oracle needs a live TaskEnv, got {type(env).__name__}; "
                           f"pass env=TaskEnv(...)")
        task = env.task
        if task.expert != ExpertPolicy.name:
            raise WAMError(f"the expert oracle simulates the scripted expert, which acts in the tasks whose spec names "
                           f"it (cube-insertion); task {task.name} has {task.expert or 'none'}: use another WAM")
        if chunk < 1:
            raise WAMError(f"the oracle's chunk must be >= 1, got {chunk}")
        if image_size is not None and image_size < 1:
            raise WAMError(f"the oracle's image_size must be >= 1 (or None), got {image_size}")
        cameras = tuple(cameras) if cameras is not None else task.cameras
        unknown = [c for c in cameras if c not in task.cameras]
        if unknown or not cameras:
            raise WAMError(f"the oracle's cameras must be among task {task.name}'s {list(task.cameras)}, got "
                           f"{list(cameras)}")
        self.env = env
        self.task = task
        self.chunk_length = int(chunk)
        self.image_size = image_size
        self.cameras = tuple(cameras)
        self.expert = copy.deepcopy(expert) if expert is not None else ExpertPolicy(task=task)

    def reset(self) -> None:
        self.expert.reset()

    def sync(self, expert: ExpertPolicy) -> None:
        """Continue from a copy of ``expert``'s phase and counters where they fit the state (e.g. the live
        expert that has been driving the env); each query still re-synchronises to the state."""
        self.expert = copy.deepcopy(expert)

    def config_dict(self) -> dict[str, Any]:
        return {"name": self.name, "chunk": self.chunk_length, "image_size": self.image_size,
                "cameras": list(self.cameras), "expert": self.expert.config_dict()}

    def predict(self, obs: Observation, instruction: str) -> WAMOutput:
        env = self.env
        if obs.step != env.step_count:
            raise WAMError(f"the observation is from step {obs.step} but the oracle's env is at step "
                           f"{env.step_count}; give the oracle the env that produced the observation")
        t0 = time.perf_counter()
        snap = env.snapshot()
        env.restore(snap)  # simulate from a restored state, as the executed chunk will run
        sim = copy.deepcopy(self.expert)
        cur = env.observe(with_images=False)
        sim.sync_to(cur)  # the phase that fits the state the chunk starts from
        start_phase = sim.phase
        actions = np.zeros((self.chunk_length, self.action_dim), np.float32)  # (H, A)
        try:
            for h in range(self.chunk_length):
                a = env.check_action(sim.act(cur))  # (A,)
                actions[h] = a
                cur, _ = env.step(a)
            t1 = time.perf_counter()
            images = env.render(self.cameras)
            t2 = time.perf_counter()
        finally:
            env.restore(snap)
            env.restore(snap)  # twice: PhysX keeps hidden solver state
        if self.image_size is not None:
            from wamplan.wam.tinywam import to_model_frames
            import torch

            images = {c: to_model_frames(torch.from_numpy(img), self.image_size).permute(1, 2, 0).numpy()
                      for c, img in images.items()}  # (s, s, 3) uint8 each
        self.expert = sim
        return WAMOutput(actions=actions, images=images,
                         timing={"query_s": time.perf_counter() - t0, "simulate_s": t1 - t0, "render_s": t2 - t1},
                         extras={"start_phase": start_phase, "expert_phase": sim.phase})
