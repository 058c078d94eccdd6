"""The planned policy and its dynamics backends, in the real env with small random models."""

import copy

import numpy as np
import pytest
import torch

from wamplan.encoders import make_encoder
from wamplan.envs.contract import CAMERAS
from wamplan.planning import CEMConfig, make_cost, make_planner
from wamplan.planning.dynamics import LearnedDynamics, PlanningContext, SimulatorDynamics
from wamplan.planning.policy import PlannedPolicy, PlannedPolicyConfig
from wamplan.policies.rollout import run_episode
from wamplan.wam.base import WAM, WAMOutput
from wamplan.worldmodel.config import PredictorConfig
from wamplan.worldmodel.predictor import WorldModelPredictor


class EchoWAM(WAM):
    """Test double: a fixed chunk (move +x, gripper open) and the current views as its 'prediction'."""

    name = "echo"

    def predict(self, obs, instruction):
        acts = np.zeros((16, 5), np.float32)
        acts[:, 0], acts[:, 4] = 0.3, 1.0
        return WAMOutput(actions=acts, images={c: obs.images[c] for c in CAMERAS})


@pytest.fixture(scope="module")
def encoder():
    return make_encoder("patch-pixels", input_size=32, patch_size=16, proj_dim=16)


def _predictor(encoder):
    torch.manual_seed(0)
    cfg = PredictorConfig(num_patches=encoder.num_patches, enc_dim=encoder.dim, frameskip=4, context=3,
                          depth=2, heads=2, head_dim=8, mlp_dim=32, proprio_emb=8, action_emb=8)
    return WorldModelPredictor(cfg).eval()


def _cem(n=8, iters=2):
    return make_planner("cem", CEMConfig(num_candidates=n, num_elites=2, iterations=iters))


def test_learned_dynamics_matches_naive_rollout(encoder):
    model = _predictor(encoder)
    dyn = LearnedDynamics(model)
    g = torch.Generator().manual_seed(1)
    ctx = PlanningContext(z=torch.randn(3, 3, encoder.num_patches, encoder.dim, generator=g),
                          q=torch.randn(3, 10, generator=g), a=torch.rand(2, 20, generator=g) * 2 - 1)
    dyn.prepare(ctx)
    cands = torch.rand(5, 16, 5, generator=g) * 2 - 1
    z = dyn.terminal(cands)
    ref, _ = model.rollout(ctx.z[None], ctx.q[None], ctx.a[None], cands.reshape(5, 4, 20), naive=True)
    assert z.shape == (5, 3, encoder.num_patches, encoder.dim)
    torch.testing.assert_close(z, ref[:, -1], rtol=1e-4, atol=1e-4)
    assert dyn.covered(16) == 16 and LearnedDynamics(_paper_like(encoder)).covered(16) == 15


def test_bfloat16_dynamics_roll_out_close_to_float32_and_return_float32(encoder):
    model = _predictor(encoder)
    with torch.no_grad():
        for p in model.parameters():  # all weights random: the zero-initialised heads would predict the input
            p.normal_(0.0, 0.2)
    dyn32, dyn16 = LearnedDynamics(model), LearnedDynamics(copy.deepcopy(model).to(torch.bfloat16))
    g = torch.Generator().manual_seed(1)
    ctx = PlanningContext(z=torch.randn(3, 3, encoder.num_patches, encoder.dim, generator=g),
                          q=torch.randn(3, 10, generator=g), a=torch.rand(2, 20, generator=g) * 2 - 1)  # float32
    cands = torch.rand(16, 16, 5, generator=g) * 2 - 1  # (B, L, A)
    for dyn in (dyn32, dyn16):
        dyn.prepare(ctx)
    z32, z16 = dyn32.terminal(cands), dyn16.terminal(cands)
    assert dyn16.dtype == torch.bfloat16 and z16.dtype == torch.float32 and z16.shape == z32.shape
    assert (z16 - z32).abs().mean() < 0.02 * z32.abs().mean()  # bf16 keeps about 3 significant digits
    target = z32[0] + 0.1 * torch.randn(z32.shape[1:], generator=g)
    c32, c16 = (make_cost("patch")(z, target) for z in (z32, z16))
    assert torch.corrcoef(torch.stack([c32, c16]))[0, 1] > 0.99  # the candidates' costs rank alike


def _paper_like(encoder):
    cfg = PredictorConfig(num_patches=encoder.num_patches, enc_dim=encoder.dim, frameskip=5, depth=1, heads=2,
                          head_dim=8, mlp_dim=16, proprio_emb=8, action_emb=8)
    return WorldModelPredictor(cfg)


def test_planned_policy_history_and_first_chunk(small_env, encoder):
    wam = EchoWAM()
    pol = PlannedPolicy(wam, _cem(), LearnedDynamics(_predictor(encoder)), encoder, make_cost("patch"))
    seen = []
    orig = pol.dynamics.prepare

    def spy(ctx):
        seen.append(ctx)
        orig(ctx)

    pol.dynamics.prepare = spy
    r = run_episode(small_env, pol, seed=0, max_steps=33)
    assert r.length == 33
    chunks = r.policy_info["chunks"]
    assert [c["step"] for c in chunks] == [0, 16, 32]
    assert [c["planned"] for c in chunks] == [False, True, True]  # first chunk open loop (paper)
    assert all(c["search_s"] > 0 for c in chunks[1:]) and r.policy_info["mean_s"]["search_s"] > 0
    # the context of the chunk at step 16: frames 8, 12, 16 and the executed actions 8..15
    ctx = seen[0]
    assert ctx.z.shape == (3, 3, encoder.num_patches, encoder.dim) and ctx.a.shape == (2, 20)
    np.testing.assert_allclose(ctx.a.numpy().reshape(8, 5), np.asarray(pol.history.executed[8:16]), atol=0)
    # frames are rendered only where a chunk boundary's history needs them: t-8, t-4, t
    assert [s for s in range(33) if pol.wants_images(s)] == [0, 8, 12, 16, 24, 28, 32]


def test_rest_history_plans_first_chunk(small_env, encoder):
    pol = PlannedPolicy(EchoWAM(), _cem(), LearnedDynamics(_predictor(encoder)), encoder, make_cost("patch"),
                        config=PlannedPolicyConfig(first_chunk="rest-history"))
    r = run_episode(small_env, pol, seed=1, max_steps=17)
    assert [c["planned"] for c in r.policy_info["chunks"]] == [True, True]


def test_simulator_oracle_replay_reproduces_prediction(small_env, encoder):
    env = small_env
    env.reset(2)
    for _ in range(5):
        env.step(np.array([0.2, 0, -0.2, 0, 1], np.float32))
    dyn = SimulatorDynamics(env, encoder)
    dyn.prepare(None)
    before = env.proprio().copy()
    g = torch.Generator().manual_seed(0)
    cands = (torch.rand(3, 16, 5, generator=g) * 2 - 1) * 0.5
    z = dyn.terminal(cands)  # (3, V, N, D)
    np.testing.assert_array_equal(env.proprio(), before)  # the state is put back
    dyn.restore()
    for a in cands[1].numpy():
        env.step(a)
    views = env.render()
    z_replay = encoder.encode(torch.from_numpy(np.stack([views[c] for c in CAMERAS])))
    torch.testing.assert_close(z_replay, z[1], rtol=0, atol=1e-5)
    assert (z[0] - z[1]).abs().max() > 1e-3  # different candidates, different outcomes


def test_oracle_objective_is_zero_at_the_chunk_that_made_the_target(small_env, encoder):
    """The oracle objective scores the chunk that produced the target views at ~0 and others above it."""
    env = small_env
    env.reset(3)
    snap = env.snapshot()
    goal = np.zeros((16, 5), np.float32)
    goal[:, 1], goal[:, 4] = 0.4, 1.0  # move +y
    env.restore(snap)
    env.restore(snap)
    for a in goal:
        env.step(a)
    target = encoder.encode(torch.from_numpy(np.stack([env.render()[c] for c in CAMERAS])))
    env.restore(snap)
    dyn = SimulatorDynamics(env, encoder)
    dyn.prepare(None)
    other = torch.from_numpy(goal).clone()
    other[:, 1] = -0.4
    costs = make_cost("patch")(dyn.terminal(torch.stack([torch.from_numpy(goal), other])), target)
    assert costs[0] < 1e-6 < 1e-3 < costs[1]


def test_planned_policy_with_simulator_dynamics_runs_an_episode(small_env, encoder):
    """The oracle steps the env inside the search's inference mode; the steps executed after the search must
    still work (no inference tensor may leak into the controller's state)."""
    pol = PlannedPolicy(EchoWAM(), _cem(4, 1), SimulatorDynamics(small_env, encoder), encoder, make_cost("patch"))
    r = run_episode(small_env, pol, seed=4, max_steps=33)
    # the first chunk runs open loop in every condition (paper §3.3), the simulator's too
    assert r.length == 33 and [c["planned"] for c in r.policy_info["chunks"]] == [False, True, True]
    assert r.policy_info["open_loop_chunks"] == {"first-chunk": 1}
    pol = PlannedPolicy(EchoWAM(), _cem(4, 1), SimulatorDynamics(small_env, encoder), encoder, make_cost("patch"),
                        config=PlannedPolicyConfig(first_chunk="rest-history"))
    r = run_episode(small_env, pol, seed=4, max_steps=17)
    assert [c["planned"] for c in r.policy_info["chunks"]] == [True, True]  # the simulator needs no history


# ---------------------------------------------------------------- paper frameskip Δ = 5 (does not divide H = 16)
class _Recorder:
    """Wraps a real cost: records the devices of what the planner hands it."""

    def __init__(self, cost):
        self.cost, self.devices = cost, set()

    def __call__(self, pred, target):
        self.devices.add((pred.device, target.device))
        return self.cost(pred, target)


def _delta5_predictor(encoder):
    torch.manual_seed(0)
    cfg = PredictorConfig(num_patches=encoder.num_patches, enc_dim=encoder.dim, frameskip=5, context=3,
                          depth=1, heads=2, head_dim=8, mlp_dim=16, proprio_emb=8, action_emb=8)
    return WorldModelPredictor(cfg).eval()


def test_frameskip_5_plans_every_chunk_after_the_first(small_env, encoder):
    """Δ = 5: the history of boundary t is t-10, t-5, t. Every chunk after the first is planned over a whole
    300-step episode, with the right frames and actions, and the cost sees tensors on the search's device."""
    cost = _Recorder(make_cost("patch"))
    pol = PlannedPolicy(EchoWAM(), _cem(4, 1), LearnedDynamics(_delta5_predictor(encoder)), encoder, cost)
    seen = []
    orig = pol.dynamics.prepare
    pol.dynamics.prepare = lambda ctx: (seen.append(ctx), orig(ctx))[1]
    r = run_episode(small_env, pol, seed=0, max_steps=300, stop_on_success=False)
    chunks = r.policy_info["chunks"]
    assert r.length == 300 and len(chunks) == 19
    assert [c["planned"] for c in chunks] == [False] + [True] * 18
    assert r.policy_info["open_loop_chunks"] == {"first-chunk": 1}
    assert [s for s in range(40) if pol.wants_images(s)] == [0, 6, 11, 16, 22, 27, 32, 38]
    # the chunk at 32: frames at 22, 27, 32 with the actions executed from 22 to 31
    ctx = seen[1]
    assert ctx.a.shape == (2, 25)
    np.testing.assert_array_equal(ctx.a.numpy().reshape(10, 5), np.asarray(pol.history.executed[22:32]))
    small_env.reset(0)
    for a in pol.history.executed[:22]:
        small_env.step(a)
    np.testing.assert_allclose(ctx.q[0].numpy(), small_env.proprio(), atol=1e-4)  # frame 0 of it is step 22
    z22 = encoder.encode(torch.from_numpy(np.stack([small_env.render()[c] for c in CAMERAS])))
    torch.testing.assert_close(ctx.z[0], z22, rtol=0, atol=1e-4)
    # 15 actions are optimised, the 16th is the WAM's (paper §3.2); every cost call on the search's device
    assert pol.dynamics.covered(16) == 15
    assert cost.devices == {(pol.device, pol.device)}


def test_a_gap_in_the_history_raises(small_env, encoder):
    """A history frame the policy never saw is an error, never a silently unplanned chunk."""
    from wamplan.planning.history import PlanningError

    pol = PlannedPolicy(EchoWAM(), _cem(4, 1), LearnedDynamics(_delta5_predictor(encoder)), encoder, make_cost("patch"))
    pol.reset(0)
    obs = small_env.reset(0, with_images=True)
    for t in range(6):
        obs, _ = small_env.step(pol.act(obs), with_images=(t + 1) % 16 == 0)  # no views at step 6
    with pytest.raises(PlanningError, match="needs the views at step 6"):
        pol.act(obs)
    pol.reset(0)
    obs = small_env.reset(0, with_images=True)
    for t in range(32):
        obs, _ = small_env.step(pol.act(obs), with_images=pol.wants_images(t + 1))
    del pol.history.frames[22]  # a gap: the frame at t-10 of the chunk at 32
    with pytest.raises(PlanningError, match=r"steps \[22\] are missing"):
        pol.act(obs)


def test_a_long_history_warms_up_open_loop_and_is_counted(small_env, encoder):
    """(H_ctx-1)Δ = 20 > 16: the chunk at 16 cannot have its history yet; it runs open loop and is counted."""
    torch.manual_seed(0)
    cfg = PredictorConfig(num_patches=encoder.num_patches, enc_dim=encoder.dim, frameskip=10, context=3,
                          depth=1, heads=2, head_dim=8, mlp_dim=16, proprio_emb=8, action_emb=8)
    pol = PlannedPolicy(EchoWAM(), _cem(4, 1), LearnedDynamics(WorldModelPredictor(cfg).eval()), encoder,
                        make_cost("patch"))
    r = run_episode(small_env, pol, seed=1, max_steps=49)
    assert [c["planned"] for c in r.policy_info["chunks"]] == [False, False, True, True]
    assert r.policy_info["open_loop_chunks"] == {"first-chunk": 1, "warm-up": 1}


def test_rest_history_context_is_the_first_frame_holding_still(small_env, encoder):
    pol = PlannedPolicy(EchoWAM(), _cem(4, 1), LearnedDynamics(_predictor(encoder)), encoder, make_cost("patch"),
                        config=PlannedPolicyConfig(first_chunk="rest-history"))
    seen = []
    orig = pol.dynamics.prepare
    pol.dynamics.prepare = lambda ctx: (seen.append(ctx), orig(ctx))[1]
    obs = small_env.reset(1, with_images=True)
    pol.reset(1)
    pol.act(obs)
    ctx = seen[0]
    z0 = encoder.encode(torch.from_numpy(np.stack([obs.images[c] for c in CAMERAS])))
    for i in range(3):
        torch.testing.assert_close(ctx.z[i], z0, rtol=0, atol=1e-5)
        np.testing.assert_array_equal(ctx.q[i].numpy(), obs.proprio)
    hold = np.tile(np.array([0, 0, 0, 0, 1], np.float32), 4)
    np.testing.assert_array_equal(ctx.a.numpy(), np.stack([hold, hold]))


def test_executed_chunk_is_the_plan(small_env, encoder):
    pol = PlannedPolicy(EchoWAM(), _cem(8, 2), LearnedDynamics(_predictor(encoder)), encoder, make_cost("patch"))
    executed = []
    r = run_episode(small_env, pol, seed=2, max_steps=32, on_obs=lambda e, o, a: executed.append(a))
    plan = pol.last_plan
    np.testing.assert_allclose(np.stack(executed[17:33]), np.clip(plan.actions.numpy(), -1, 1), atol=1e-6)
    assert r.policy_info["chunks"][1]["planned"] and not np.allclose(executed[17:33], executed[1:17])


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_planned_policy_on_cuda(small_env, encoder):
    """Models on the GPU, env on the CPU: every tensor the cost sees is on the GPU, and the plan comes back."""
    cuda = torch.device("cuda")
    enc = make_encoder("patch-pixels", input_size=32, patch_size=16, proj_dim=16).to(cuda)
    cost = _Recorder(make_cost("patch"))
    pol = PlannedPolicy(EchoWAM(), _cem(4, 1), LearnedDynamics(_predictor(enc).to(cuda)), enc, cost)
    r = run_episode(small_env, pol, seed=0, max_steps=33)
    assert [c["planned"] for c in r.policy_info["chunks"]] == [False, True, True]
    assert {d.type for pair in cost.devices for d in pair} == {"cuda"}


def test_search_tensors_follow_the_dynamics_device(small_env, encoder):
    """The world model on another device than the encoder and the env (here torch's shape-only 'meta' device, which
    exists on every machine): the target, the history and the candidates the cost compares all live on the
    dynamics' device. Before, the target stayed on the CPU and the cost failed on a GPU."""
    meta = torch.device("meta")
    pol = PlannedPolicy(EchoWAM(), _cem(4, 1), LearnedDynamics(_predictor(encoder).to(meta)), encoder,
                        make_cost("patch"))
    assert pol.device == meta
    obs = small_env.reset(0, with_images=True)
    pol.reset(0)
    for t in range(16):
        obs, _ = small_env.step(pol.act(obs), with_images=pol.wants_images(t + 1))
    target = pol.encode(obs.images)  # (V, N, D): the frame at 16 is also the chunk's current frame
    assert target.device == meta and all(z.device == q.device == meta for z, q in pol.history.frames.values())
    pol.history.frames[16] = (target, torch.as_tensor(obs.proprio, device=meta))  # what act(obs) stores before planning
    ctx = pol.history.planning_context(16)
    assert {ctx.z.device, ctx.q.device, ctx.a.device} == {meta}
    pol.dynamics.prepare(ctx)
    cands = torch.zeros(4, 16, 5, device=meta)
    cost = pol.cost(pol.dynamics.terminal(cands), target)  # would raise if the two sat on different devices
    assert cost.shape == (4,) and cost.device == meta


def test_an_imagined_history_sees_only_boundaries_and_predicts_the_frames_between(small_env, encoder):
    """history="imagined": the frames at t-8 and t-4 are the model's rollout from the previous boundary's context
    (at step 16: frame 0 alone) under the actions executed since; the boundary's own frame is seen."""
    model = _predictor(encoder)
    with torch.no_grad():
        for p in model.parameters():  # random weights throughout, so the predictions differ from the input
            p.normal_(0.0, 0.2)
    pol = PlannedPolicy(EchoWAM(), _cem(4, 1), LearnedDynamics(model), encoder, make_cost("patch"),
                        config=PlannedPolicyConfig(history="imagined"))
    seen = []
    orig = pol.dynamics.prepare
    pol.dynamics.prepare = lambda ctx: (seen.append(ctx), orig(ctx))[1]
    assert [s for s in range(33) if pol.wants_images(s)] == [0, 16, 32]
    obs = small_env.reset(0, with_images=True)
    pol.reset(0)
    first = (pol.encode(obs.images), torch.as_tensor(obs.proprio))
    for t in range(33):
        obs, _ = small_env.step(pol.act(obs), with_images=pol.wants_images(t + 1))
        if t == 15:
            now = pol.encode(obs.images)
    assert [c["planned"] for c in pol.chunks] == [False, True, True]
    acts = torch.from_numpy(np.stack(pol.history.executed[:12]).astype(np.float32))  # (12, A)
    z, q = model.rollout(first[0][None, None], first[1][None, None].float(), torch.zeros(1, 0, 20),
                         acts.reshape(1, 3, 20))  # the frames at 4, 8, 12 from frame 0 alone
    ctx = seen[0]  # the chunk at step 16: frames 8, 12 imagined, 16 seen
    torch.testing.assert_close(ctx.z[:2], z[0, 1:], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(ctx.q[:2], q[0, 1:], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(ctx.z[2], now, rtol=0, atol=0)
    assert not torch.allclose(ctx.z[1], ctx.z[2], atol=1e-3)
    np.testing.assert_allclose(ctx.a.numpy().reshape(8, 5), np.asarray(pol.history.executed[8:16]), atol=0)
    acts = torch.from_numpy(np.stack(pol.history.executed[16:28]).astype(np.float32)).reshape(1, 3, 20)
    z, _ = model.rollout(ctx.z[None], ctx.q[None], ctx.a[None], acts)  # the chunk at 32 rolls on from 16's context
    torch.testing.assert_close(seen[1].z[:2], z[0, 1:], rtol=1e-4, atol=1e-4)


def test_an_imagined_history_is_refused_where_nothing_can_imagine_it(small_env, encoder):
    from wamplan.planning.history import PlanningError

    imagined = PlannedPolicyConfig(history="imagined")
    with pytest.raises(PlanningError, match="keeps none: leave --history at seen"):
        PlannedPolicy(EchoWAM(), _cem(), SimulatorDynamics(small_env, encoder), encoder, make_cost("patch"),
                      config=imagined)
    with pytest.raises(PlanningError, match="frameskip 5, which does not divide the 16 steps"):
        PlannedPolicy(EchoWAM(), _cem(), LearnedDynamics(_delta5_predictor(encoder)), encoder, make_cost("patch"),
                      config=imagined)
