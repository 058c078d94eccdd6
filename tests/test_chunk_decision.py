"""The planned policy's pieces without a simulator: ChunkDecision (every open-loop reason, for the setting that
causes it; what runs is what it says), FrameHistory (which frames, the rest state, the missing-frame error) and
the Gates. Toy models make every decision certain: a view's embedding is its mean pixel, a chunk's predicted
outcome is the mean of its first action dimension, so a WAM chunk at the target's value cannot be improved on."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from wamplan.config import ConfigError
from wamplan.envs.contract import ACTION_DIM, CAMERAS, HOLD_ACTION, PROPRIO_DIM, Observation
from wamplan.planning import CEMConfig, make_cost, make_planner
from wamplan.planning.decision import OPEN_LOOP, ChunkDecision, ChunkTimings
from wamplan.planning.dynamics import Dynamics
from wamplan.planning.gates import Gates
from wamplan.planning.history import FrameHistory, PlanningError
from wamplan.planning.policy import PlannedPolicy, PlannedPolicyConfig
from wamplan.wam.base import WAM, WAMOutput

H = 16
TARGET = 128  # the pixel value of every predicted view: its embedding is 128 / 255


class ToyEncoder:
    """A view (H, W, 3) uint8 -> one token (1, 1): its mean pixel / 255."""

    device = torch.device("cpu")

    def encode(self, x: torch.Tensor) -> torch.Tensor:  # (B, H, W, 3) -> (B, 1, 1)
        return (x.float().mean(dim=(1, 2, 3)) / 255.0)[:, None, None]

    def config_dict(self):
        return {"name": "toy"}


class ToyWAM(WAM):
    """A constant chunk whose first action dimension is ``a0``; every predicted view is the TARGET grey."""

    name = "toy"

    def __init__(self, a0: float):
        self.a0 = a0

    def predict(self, obs, instruction):
        acts = np.zeros((H, ACTION_DIM), np.float32)
        acts[:, 0], acts[:, 4] = self.a0, 1.0
        return WAMOutput(actions=acts, images={c: np.full((4, 4, 3), TARGET, np.uint8) for c in CAMERAS})


class ToyDynamics(Dynamics):
    """Predicted embedding of a chunk (B, L, A) -> (B, V, 1, 1): the mean of its first action dimension.
    ``frameskip``/``context`` given: it asks for a history as a learned model does."""

    def __init__(self, frameskip: int | None = None, context: int = 3):
        self.needs_history = frameskip is not None
        if frameskip is not None:
            self.frameskip, self.context = frameskip, context
        self.contexts = []

    @property
    def device(self):
        return torch.device("cpu")

    def covered(self, chunk):
        return chunk

    def prepare(self, context):
        self.contexts.append(context)

    def terminal(self, actions):
        return actions[:, :, 0].mean(dim=1)[:, None, None, None].expand(-1, len(CAMERAS), 1, 1)  # (B, V, 1, 1)


def _obs(step: int, images: bool = True) -> Observation:
    views = {c: np.full((4, 4, 3), step % 256, np.uint8) for c in CAMERAS} if images else None
    return Observation(step=step, proprio=np.full(PROPRIO_DIM, step, np.float32), images=views)


def _policy(a0: float = 0.2, dynamics: Dynamics | None = None, **cfg) -> PlannedPolicy:
    planner = make_planner("cem", CEMConfig(num_candidates=16, num_elites=4, iterations=3))
    return PlannedPolicy(ToyWAM(a0), planner, dynamics or ToyDynamics(), ToyEncoder(), make_cost("patch"),
                         config=PlannedPolicyConfig(**cfg))


# ------------------------------------------------------------------ ChunkDecision
@pytest.mark.parametrize("a0, cfg, dynamics, step, reason", [
    (0.2, {}, None, 0, "first-chunk"),  # the paper: chunk 1 open loop
    (0.2, dict(first_chunk="rest-history"), None, 0, None),  # planned from a rest state
    (0.2, {}, None, H, None),
    (0.2, {}, ToyDynamics(frameskip=10), H, "warm-up"),  # its history reaches step -4
    (0.2, dict(gate_threshold=1.0), None, H, "gated"),  # every cost is below 1
    (TARGET / 255, dict(accept_margin=0.5), None, H, "rejected"),  # nor can the plan
])
def test_each_open_loop_reason_comes_from_its_setting(a0, cfg, dynamics, step, reason):
    pol = _policy(a0, dynamics, **cfg)
    pol.reset(0)
    d = pol.plan_chunk(_obs(step))  # standalone: the frame it needs joins the history
    assert d.step == step and d.reason == reason and d.planned == (reason is None)
    assert d.seed.shape == d.executed.shape == (H, ACTION_DIM)
    np.testing.assert_array_equal(d.executed, d.seed if reason else d.plan)
    assert (d.plan is not None) == (reason in (None, "rejected"))  # searched or not
    assert (d.target is not None) == (reason not in ("first-chunk", "warm-up"))
    assert pol.info()["chunks"] == [d.record()] and pol.last_decision is d
    assert pol.info()["open_loop_chunks"] == ({} if reason is None else {reason: 1})
    if reason in ("gated", "rejected"):
        assert d.costs.seed is not None and d.record()["seed_cost"] == d.costs.seed
    if reason == "rejected":
        assert d.costs.plan >= (1 - 0.5) * d.costs.seed and d.record()["plan_cost"] == d.costs.plan
    if reason is None:
        assert d.costs.best < d.costs.seed and d.correction[0] > 0  # toward the target: a0 grows
        assert d.record()["correction"] == list(d.correction)
    assert set(OPEN_LOOP) == {"first-chunk", "warm-up", "gated", "rejected"}


def test_the_actions_run_are_the_decisions_executed_chunk():
    pol = _policy(0.2, accept_margin=0.0, warm_start="residual")
    pol.reset(3)
    acts, decisions = [], []
    for t in range(3 * H):
        acts.append(pol.act(_obs(t, images=pol.wants_images(t))))
        if t % H == 0:
            decisions.append(pol.last_decision)
    assert [d.step for d in decisions] == [0, H, 2 * H] and [d.reason for d in decisions] == ["first-chunk", None, None]
    for d in decisions:
        np.testing.assert_array_equal(np.stack(acts[d.step:d.step + H]), d.executed)
    assert pol.info()["chunks"] == [d.record() for d in decisions]
    assert "init_cost" in pol.chunks[2] and decisions[2].costs.init is not None  # warm-started from chunk 16


def test_plan_chunk_refuses_a_step_inside_a_chunk():
    pol = _policy()
    pol.reset(0)
    with pytest.raises(PlanningError, match="chunk boundaries"):
        pol.plan_chunk(_obs(5))


def test_a_decision_checks_itself():
    seed = np.zeros((H, ACTION_DIM), np.float32)
    with pytest.raises(ConfigError, match="reason must be None or one of"):
        ChunkDecision(0, seed, seed, "tired")
    with pytest.raises(ConfigError, match="needs a plan"):
        ChunkDecision(0, seed, seed, None)
    with pytest.raises(ConfigError, match="one shape"):
        ChunkDecision(0, seed, seed[:4], "gated")


def test_each_timing_of_a_chunk_is_its_own_stages():
    """A record's wam_s, target_encode_s and search_s are the seconds of the WAM query, the target's encoding and
    the search: each stage of these toys sleeps a different time, and each timing holds at least its own stage's
    (a timing swapped with another would hold the shorter one)."""
    import time

    naps = dict(wam_s=0.05, target_encode_s=0.15, search_s=0.3)

    class SlowWAM(ToyWAM):
        def predict(self, obs, instruction):
            time.sleep(naps["wam_s"])
            return super().predict(obs, instruction)

    class SlowEncoder(ToyEncoder):
        def encode(self, x):
            time.sleep(naps["target_encode_s"])
            return super().encode(x)

    class SlowDynamics(ToyDynamics):
        def prepare(self, context):  # part of the search
            time.sleep(naps["search_s"])
            super().prepare(context)

    pol = PlannedPolicy(SlowWAM(0.2), make_planner("cem", CEMConfig(num_candidates=4, num_elites=2, iterations=1)),
                        SlowDynamics(), SlowEncoder(), make_cost("patch"))
    pol.reset(0)
    rec = pol.plan_chunk(_obs(H)).record()
    assert list(rec)[:5] == ["step", "planned", "wam_s", "target_encode_s", "search_s"] and rec["planned"]
    for key, nap in naps.items():
        assert rec[key] >= nap, (key, rec)
    assert pol.info()["mean_s"] == {key: rec[key] for key in naps}
    timings = ChunkTimings(wam_s=1.0, target_encode_s=2.0, search_s=3.0)
    seed = np.zeros((H, ACTION_DIM), np.float32)
    rec = ChunkDecision(H, seed, seed, "gated", timings=timings).record()
    assert (rec["wam_s"], rec["target_encode_s"], rec["search_s"]) == (1.0, 2.0, 3.0)


# ------------------------------------------------------------------ FrameHistory
def _history(rest_state=False) -> FrameHistory:
    encode = (lambda views: torch.full((len(CAMERAS), 1, 1), float(views["front"][0, 0, 0])))  # (V, 1, 1)
    return FrameHistory(H, 4, 3, encode, torch.device("cpu"), rest_state=rest_state, hold_action=HOLD_ACTION)


def test_history_keeps_the_frames_of_each_boundary_and_hands_them_with_the_actions_between():
    hist = _history()
    assert [s for s in range(40) if hist.wants(s)] == [0, 8, 12, 16, 24, 28, 32]
    for t in range(2 * H + 1):
        hist.observe(_obs(t, images=hist.wants(t)))
        hist.record_action(np.full(ACTION_DIM, t / 100, np.float32))
    assert sorted(hist.frames) == [8, 12, 16, 24, 28, 32]  # frame 0 is no longer needed
    ctx = hist.planning_context(2 * H)
    assert ctx.z[:, 0, 0, 0].tolist() == [24.0, 28.0, 32.0] and ctx.q[:, 0].tolist() == [24.0, 28.0, 32.0]
    np.testing.assert_allclose(ctx.a.numpy().reshape(8, ACTION_DIM)[:, 0], np.arange(24, 32) / 100, rtol=1e-6)
    assert hist.real(H) and not hist.real(4) and hist.planning_context(4) is None  # before step 0: no history


def test_a_rest_state_history_repeats_the_first_frame_holding_still():
    hist = _history(rest_state=True)
    hist.observe(_obs(0))
    ctx = hist.planning_context(0)
    assert ctx.z[:, 0, 0, 0].tolist() == [0.0, 0.0, 0.0]
    np.testing.assert_array_equal(ctx.a.numpy(), np.tile(HOLD_ACTION, (2, 4)))


def test_a_missing_frame_is_an_error():
    hist = _history()
    for t in range(H):
        if t != 12:  # frame 12 is never shown
            hist.observe(_obs(t))
        hist.record_action(np.zeros(ACTION_DIM, np.float32))
    hist.observe(_obs(H))
    with pytest.raises(PlanningError, match=r"history frames at steps \[12\] are missing"):
        hist.planning_context(H)
    with pytest.raises(PlanningError, match="needs the views at step 24"):
        hist.observe(_obs(24, images=False))
    hist.observe(_obs(20, images=False))  # not a history frame: nothing needed


def test_a_learned_models_history_reaches_its_dynamics():
    dyn = ToyDynamics(frameskip=4)
    pol = _policy(0.2, dyn)
    pol.reset(0)
    for t in range(H + 1):
        pol.act(_obs(t, images=pol.wants_images(t)))
    (ctx,) = dyn.contexts  # the chunk at 16: frames 8, 12, 16
    assert ctx.z[:, 0, 0, 0].tolist() == pytest.approx([8 / 255, 12 / 255, 16 / 255])
    np.testing.assert_array_equal(ctx.a.numpy().reshape(8, ACTION_DIM), np.stack(pol.history.executed[8:16]))


# ------------------------------------------------------------------ Gates
def test_gates_decide_before_and_after_the_search():
    calls = []

    def plan_cost(value):
        return lambda: calls.append(value) or value

    assert Gates().before_search(None) is None and not Gates().needs_wam_cost
    assert Gates().after_search(None, plan_cost(1.0)) == (None, None) and not calls
    gate = Gates(threshold=0.1)
    assert gate.needs_wam_cost
    assert [gate.before_search(c) for c in (0.1, 0.3)] == ["gated", None]
    accept = Gates(accept_margin=0.2)
    assert accept.after_search(1.0, plan_cost(0.7)) == (None, 0.7)  # 0.7 <= (1 - 0.2) x 1.0: the plan runs
    assert accept.after_search(1.0, plan_cost(0.9)) == ("rejected", 0.9) and calls == [0.7, 0.9]
    assert Gates(accept_margin=0.0).after_search(1.0, plan_cost(1.0)) == (None, 1.0)  # not worse: kept
    assert PlannedPolicyConfig(gate_threshold=0.1, accept_margin=0.2).gates == Gates(threshold=0.1, accept_margin=0.2)


@pytest.mark.parametrize("kw, match", [(dict(threshold=float("nan")), "threshold"),
                                       (dict(accept_margin=1.0), "accept_margin must be in")])
def test_gates_refuse_settings_that_cannot_work(kw, match):
    with pytest.raises(ConfigError, match=match):
        Gates(**kw)


# ------------------------------------------------------------------ the task
def test_the_policy_plans_for_its_wams_task_and_refuses_models_made_for_another():
    from wamplan.envs.spec import get_task
    from wamplan.errors import UserError

    peg = get_task("peg-insertion-side")
    pol = PlannedPolicy(ToyWAM(0.2), make_planner("cem-gripper"), ToyDynamics(), ToyEncoder(), make_cost("patch"))
    assert pol.task.name == "cube-insertion" and pol.planner.config.gripper_dim == 4  # filled from the WAM's task
    assert pol.cameras == CAMERAS  # the dynamics names none: the task's
    other = ToyDynamics(frameskip=4)  # a learned model's
    other.task = peg
    with pytest.raises(UserError, match="checkpoint of the world model was made for task 'peg-insertion-side', but "
                                        "this run uses task 'cube-insertion'"):
        PlannedPolicy(ToyWAM(0.2), make_planner("cem"), other, ToyEncoder(), make_cost("patch"))
    target = ToyWAM(0.2)
    target.task = peg
    with pytest.raises(UserError, match=r"WAM toy \(the target\) was made for task 'peg-insertion-side'"):
        PlannedPolicy(ToyWAM(0.2), make_planner("cem"), ToyDynamics(), ToyEncoder(), make_cost("patch"),
                      target_wam=target)


def test_views_are_stacked_in_the_dynamics_camera_order():
    dyn = ToyDynamics()
    dyn.cameras = ("wrist", "front", "side")
    pol = PlannedPolicy(ToyWAM(0.2), make_planner("cem"), dyn, ToyEncoder(), make_cost("patch"))
    views = {c: np.full((4, 4, 3), v, np.uint8) for c, v in (("front", 0), ("side", 51), ("wrist", 102))}
    assert pol.encode(views)[:, 0, 0].tolist() == pytest.approx([0.4, 0.0, 0.2])
