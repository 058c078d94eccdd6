"""Which actions a planned policy executes, step by step, and which it hands the world model as history.

Every other planned-policy test uses a stand-in WAM whose 16 actions are identical, so none of them can tell
*which* action runs at a step. Here the WAM's 16 actions all differ (and differ between chunks), the planner's
plan differs from every one of them, and the policy is driven through its public ``act()`` / ``info()`` only,
at the mini preset's frameskip 4 and the paper's 5 (where the plan covers 15 of 16 steps and the 16th is the
WAM's own). No simulator: observations are made up, so the test runs in well under a second.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from wamplan.encoders import make_encoder
from wamplan.envs.contract import ACTION_DIM, CAMERAS, Observation
from wamplan.planning import make_cost
from wamplan.planning.base import IterationStats, Planner, PlanResult
from wamplan.planning.dynamics import Dynamics
from wamplan.planning.policy import PlannedPolicy
from wamplan.wam.base import WAM, WAMOutput

H = 16  # the WAM's chunk


def wam_chunk(step: int) -> np.ndarray:
    """(H, A) the WAM's chunk at boundary ``step``: every entry distinct, within [-1, 1]."""
    i = np.arange(H, dtype=np.float32)[:, None]  # (H, 1)
    d = np.arange(ACTION_DIM, dtype=np.float32)[None]  # (1, A)
    return (0.01 * i + 0.2 * d + 0.003 * step - 0.6).astype(np.float32)  # (H, A)


def plan_of(init: np.ndarray) -> np.ndarray:
    """What the stand-in planner returns for the chunk ``init`` (L, A): distinct from every WAM action."""
    return (-0.5 * init + 0.05).astype(np.float32)


class DistinctWAM(WAM):
    name = "distinct"

    def predict(self, obs: Observation, instruction: str) -> WAMOutput:
        return WAMOutput(actions=wam_chunk(obs.step), images={c: obs.images[c] for c in CAMERAS})


class StandInDynamics(Dynamics):
    """A learned model's shape without a model: frameskip Δ, three history frames; it records every context."""

    needs_history = True

    def __init__(self, frameskip: int, encoder):
        self.frameskip, self.context = frameskip, 3
        self.shape = (len(CAMERAS), encoder.num_patches, encoder.dim)
        self.contexts: list = []

    @property
    def device(self) -> torch.device:
        return torch.device("cpu")

    def covered(self, chunk: int) -> int:
        return self.frameskip * (chunk // self.frameskip)

    def prepare(self, context) -> None:
        self.contexts.append(context)

    def terminal(self, actions: torch.Tensor) -> torch.Tensor:
        return torch.zeros(actions.shape[0], *self.shape)  # (B, V, N, D)


class StandInPlanner(Planner):
    name = "stand-in"

    def __init__(self):
        super().__init__()
        self.inits: list[np.ndarray] = []

    def plan(self, seed_actions, objective, *, generator=None, seed=None) -> PlanResult:
        init = seed_actions.cpu().numpy()  # (H_opt, A)
        self.inits.append(init)
        plan = torch.from_numpy(plan_of(init))  # (H_opt, A)
        stats = IterationStats(0, 0.0, 0.0, 0.0, 0.0, 0.0)
        return PlanResult(actions=plan, mean=plan, std=torch.zeros_like(plan), best_actions=plan, best_cost=0.0,
                          history=[stats], num_evaluations=1)


@pytest.fixture(scope="module")
def encoder():
    return make_encoder("patch-pixels", input_size=32, patch_size=16, proj_dim=16)


def _drive(policy: PlannedPolicy, steps: int) -> np.ndarray:
    """Run ``steps`` steps through act(), with views exactly where the policy asks for them -> (steps, A)."""
    rng = np.random.default_rng(0)
    policy.reset(0)
    out = []
    for t in range(steps):
        images = {c: rng.integers(0, 256, (32, 32, 3), dtype=np.uint8) for c in CAMERAS} \
            if policy.wants_images(t) else None
        out.append(policy.act(Observation(step=t, proprio=np.full(10, t, np.float32), images=images)))
    return np.stack(out)  # (steps, A)


@pytest.mark.parametrize("frameskip", [4, 5])
def test_each_step_runs_the_action_the_chunk_rules_name(encoder, frameskip):
    dyn, planner = StandInDynamics(frameskip, encoder), StandInPlanner()
    policy = PlannedPolicy(DistinctWAM(), planner, dyn, encoder, make_cost("patch"))
    executed = _drive(policy, 3 * H)  # (48, A): chunks at steps 0, 16, 32
    covered = dyn.covered(H)  # 16 at Δ = 4; 15 at Δ = 5, the last step is the WAM's
    assert covered == (16 if frameskip == 4 else 15)

    # chunk 0: the WAM's chunk, open loop, action by action
    np.testing.assert_array_equal(executed[:H], wam_chunk(0))
    for t0 in (H, 2 * H):  # planned chunks: the plan over the covered steps, then the WAM's own tail
        np.testing.assert_array_equal(planner.inits[t0 // H - 1], wam_chunk(t0)[:covered])  # searched from the WAM's
        expected = np.concatenate([plan_of(wam_chunk(t0)[:covered]), wam_chunk(t0)[covered:]])  # (H, A)
        np.testing.assert_array_equal(executed[t0:t0 + H], expected)
    if covered < H:  # the tail is the WAM's last action, not the plan's last one repeated
        assert not np.array_equal(executed[2 * H - 1], executed[2 * H - 2])
        np.testing.assert_array_equal(executed[2 * H - 1], wam_chunk(H)[-1])

    info = policy.info()
    assert [c["step"] for c in info["chunks"]] == [0, H, 2 * H]
    assert [c["planned"] for c in info["chunks"]] == [False, True, True]
    assert info["open_loop_chunks"] == {"first-chunk": 1} and info["planned_chunks"] == 2


@pytest.mark.parametrize("frameskip", [4, 5])
def test_the_world_model_gets_the_executed_actions_as_history(encoder, frameskip):
    """At boundary t the context holds the frames t-2Δ, t-Δ, t and the actions executed between them, in Δ-step
    blocks: the open-loop WAM actions before 16, then the plan and (at Δ = 5) the WAM's tail action at 31."""
    dyn = StandInDynamics(frameskip, encoder)
    policy = PlannedPolicy(DistinctWAM(), StandInPlanner(), dyn, encoder, make_cost("patch"))
    executed = _drive(policy, 2 * H + 1)  # through the boundary at 32
    assert len(dyn.contexts) == 2  # prepared at the boundaries 16 and 32
    for t, ctx in zip((H, 2 * H), dyn.contexts):
        first = t - 2 * frameskip
        assert ctx.a.shape == (2, frameskip * ACTION_DIM)
        np.testing.assert_array_equal(ctx.a.numpy().reshape(2 * frameskip, ACTION_DIM), executed[first:t])
        np.testing.assert_array_equal(ctx.q[:, 0].numpy(), [first, t - frameskip, t])  # proprio of those frames
    if frameskip == 5:  # the block before 32 ends with step 31's action: the WAM's, as executed
        np.testing.assert_array_equal(dyn.contexts[1].a[-1, -ACTION_DIM:].numpy(), wam_chunk(H)[-1])
