"""The planned policy and its dynamics backends, in the real env with small random models."""

import numpy as np
import pytest
import torch

from wamplan.encoders import make_encoder
from wamplan.envs.core import EnvConfig, InsertionEnv
from wamplan.envs.rollout import run_episode
from wamplan.planning import CEMConfig, make_cost, make_planner
from wamplan.planning.dynamics import LearnedDynamics, PlanningContext, SimulatorDynamics
from wamplan.planning.policy import PlannedPolicy, PlannedPolicyConfig
from wamplan.policies.base import CAMERAS
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
def small_env():
    e = InsertionEnv(EnvConfig(camera_size=64))
    yield e
    e.close()


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
    np.testing.assert_allclose(ctx.a.numpy().reshape(8, 5), np.asarray(pol._executed[8:16]), atol=0)
    assert pol.wants_images(4) and pol.wants_images(16) and not pol.wants_images(5)


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
    assert r.length == 33 and [c["planned"] for c in r.policy_info["chunks"]] == [True, True, True]  # no history
