"""Gated planning, warm starts and the uncertainty-aware (ensemble) cost of the planned policy."""

import dataclasses

import numpy as np
import pytest
import torch

from wamplan.errors import UserError
from wamplan.planning import CEMConfig, make_cost, make_planner
from wamplan.planning.dynamics import Dynamics, EnsembleDynamics, LearnedDynamics, PlanningContext, learned_dynamics
from wamplan.planning.history import PlanningError
from wamplan.planning.policy import PlannedPolicy, PlannedPolicyConfig
from wamplan.policies.rollout import run_episode
from wamplan.worldmodel.predictor import WorldModelPredictor
from test_planned_policy import EchoWAM, _predictor, encoder  # noqa: F401 (fixture; small_env is in conftest)


def _cem(n=8, iters=2):
    return make_planner("cem", CEMConfig(num_candidates=n, num_elites=2, iterations=iters))


def _policy(encoder, **cfg):
    return PlannedPolicy(EchoWAM(), _cem(), LearnedDynamics(_predictor(encoder)), encoder, make_cost("patch"),
                         config=PlannedPolicyConfig(**cfg))


def _ctx(encoder, seed=1):
    g = torch.Generator().manual_seed(seed)
    return PlanningContext(z=torch.randn(3, 3, encoder.num_patches, encoder.dim, generator=g),
                           q=torch.randn(3, 10, generator=g), a=torch.rand(2, 20, generator=g) * 2 - 1)


# ------------------------------------------------------------------ gated planning
def test_gate_skips_the_search_below_the_threshold_and_counts_it(small_env, encoder):
    always = run_episode(small_env, _policy(encoder), seed=0, max_steps=49).policy_info
    assert always["open_loop_chunks"] == {"first-chunk": 1} and always["planned_chunks"] == 3
    c16 = always["chunks"][1]["seed_cost"]
    gated = run_episode(small_env, _policy(encoder, gate_threshold=float("inf")), seed=0, max_steps=49).policy_info
    assert gated["open_loop_chunks"] == {"first-chunk": 1, "gated": 3} and gated["planned_chunks"] == 0
    assert all(c["open_loop"] == "gated" and np.isfinite(c["seed_cost"]) for c in gated["chunks"][1:])
    assert gated["chunks"][1]["seed_cost"] == pytest.approx(c16, rel=1e-4)  # the same cost as the planner's seed
    # the chunk at step 16 follows the same open-loop first chunk: the gate decides on c16 alone
    just_above = run_episode(small_env, _policy(encoder, gate_threshold=c16 * 1.001), seed=0, max_steps=17)
    just_below = run_episode(small_env, _policy(encoder, gate_threshold=c16 * 0.999), seed=0, max_steps=17)
    assert just_above.policy_info["chunks"][1].get("open_loop") == "gated"
    assert just_below.policy_info["chunks"][1]["planned"] and "open_loop" not in just_below.policy_info["chunks"][1]


def test_a_gated_chunk_executes_the_wams_chunk(small_env, encoder):
    executed = []
    run_episode(small_env, _policy(encoder, gate_threshold=1e9), seed=2, max_steps=32,
                on_obs=lambda e, o, a: executed.append(a))
    wam = np.zeros((16, 5), np.float32)
    wam[:, 0], wam[:, 4] = 0.3, 1.0  # EchoWAM's chunk
    np.testing.assert_array_equal(np.asarray(executed[16:32]), wam)


# ------------------------------------------------------------------ trust test (accept margin)
def test_accept_margin_keeps_the_wams_chunk_unless_the_plan_is_clearly_better(small_env, encoder):
    wam = np.zeros((16, 5), np.float32)
    wam[:, 0], wam[:, 4] = 0.3, 1.0  # EchoWAM's chunk
    always = run_episode(small_env, _policy(encoder, accept_margin=0.0), seed=2, max_steps=17).policy_info
    (c,) = [c for c in always["chunks"] if c["step"] == 16]
    assert c["planned"] and c["plan_cost"] <= c["seed_cost"]  # margin 0: any improvement is executed
    gain = 1 - c["plan_cost"] / c["seed_cost"]
    for margin, planned in ((gain * 0.5, True), (min(gain * 1.5 + 1e-6, 0.99), False)):
        executed = []
        info = run_episode(small_env, _policy(encoder, accept_margin=margin), seed=2, max_steps=32,
                           on_obs=lambda e, o, a: executed.append(a)).policy_info
        (c2,) = [c for c in info["chunks"] if c["step"] == 16]
        assert c2["planned"] == planned and c2["plan_cost"] == pytest.approx(c["plan_cost"], rel=1e-4)
        if not planned:
            assert c2["open_loop"] == "rejected" and info["open_loop_chunks"]["rejected"] == 1
            np.testing.assert_array_equal(np.asarray(executed[17:33]), wam)  # the WAM's chunk, untouched
    warm = _policy(encoder, accept_margin=0.99, warm_start="residual")
    run_episode(small_env, warm, seed=2, max_steps=17)
    assert warm.chunks[1]["open_loop"] == "rejected" and warm._correction is None  # a rejected plan never carries over
    with pytest.raises(ValueError, match="accept_margin must be in"):
        PlannedPolicyConfig(accept_margin=1.0)


# ------------------------------------------------------------------ the record
def test_a_planned_chunks_record_says_what_planning_changed(small_env, encoder):
    wam = np.zeros((16, 5), np.float32)
    wam[:, 0], wam[:, 4] = 0.3, 1.0  # EchoWAM's chunk
    executed = []  # on_obs sees (reset, None) first, then the action of each step: executed[17:33] = steps 16..31
    info = run_episode(small_env, _policy(encoder), seed=0, max_steps=32,
                       on_obs=lambda e, o, a: executed.append(a)).policy_info
    (c,) = [c for c in info["chunks"] if c["step"] == 16]
    assert c["planned"] and not np.array_equal(np.asarray(executed[17:33]), wam)
    # the executed chunk minus the WAM's, mean per action dim
    np.testing.assert_allclose(c["correction"], (np.asarray(executed[17:33]) - wam).mean(0), atol=1e-4)


# ------------------------------------------------------------------ warm start
def _spy_inits(pol):
    inits, plan = [], pol.planner.plan

    def spy(seed_actions, objective, **kw):
        inits.append(seed_actions.clone())
        return plan(seed_actions, objective, **kw)

    pol.planner.plan = spy
    return inits


@pytest.mark.parametrize("weight", [1.0, 0.5])
def test_residual_warm_start_carries_the_previous_correction(small_env, encoder, weight):
    pol = _policy(encoder, warm_start="residual", warm_weight=weight)
    inits = _spy_inits(pol)
    plans = []
    run_episode(small_env, pol, seed=0, max_steps=33,
                on_obs=lambda e, o, a: plans.append(pol.last_plan.actions.clone() if pol.last_plan else None))
    wam = torch.zeros(16, 5)
    wam[:, 0], wam[:, 4] = 0.3, 1.0  # EchoWAM's chunk
    torch.testing.assert_close(inits[0], wam)  # chunk 16: nothing planned before, the WAM's chunk
    want = wam.clone()
    want[:, :4] += weight * (plans[31] - wam)[:, :4]  # chunk 32: plus the chunk-16 correction, arm only
    torch.testing.assert_close(inits[1], want)
    assert len(inits) == 2 and "init_cost" in pol.chunks[2] and "init_cost" not in pol.chunks[1]


def test_no_warm_start_seeds_every_search_with_the_wams_chunk(small_env, encoder):
    pol = _policy(encoder)
    inits = _spy_inits(pol)
    run_episode(small_env, pol, seed=0, max_steps=33)
    assert len(inits) == 2 and torch.equal(inits[0], inits[1])


# ------------------------------------------------------------------ ensemble / uncertainty-aware cost
def test_identical_members_do_not_disagree(encoder):
    model = _predictor(encoder)
    ens = EnsembleDynamics([LearnedDynamics(model), LearnedDynamics(model)])
    single = LearnedDynamics(model)
    ctx = _ctx(encoder)
    ens.prepare(ctx)
    single.prepare(ctx)
    cands = torch.rand(4, 16, 5, generator=torch.Generator().manual_seed(0)) * 2 - 1
    z, spread = ens.predict(cands)
    assert torch.equal(spread, torch.zeros(4))
    torch.testing.assert_close(z, single.terminal(cands))
    assert ens.covered(16) == 16 and ens.needs_history and ens.frameskip == 4 and ens.context == 3
    other = WorldModelPredictor(dataclasses.replace(model.cfg, frameskip=8)).eval()
    with pytest.raises(UserError, match=r"ensemble members differ in frameskip \[4, 8\]"):  # one line, not a trace
        EnsembleDynamics([LearnedDynamics(model), LearnedDynamics(other)])


def test_disagreement_is_the_variance_across_members(encoder):
    a, b = _predictor(encoder), _predictor(encoder)
    torch.manual_seed(5)
    b = WorldModelPredictor(b.cfg).eval()  # other weights
    (dyn, enc) = learned_dynamics([(a, encoder), (b, encoder)])
    assert isinstance(dyn, EnsembleDynamics) and enc is encoder
    dyn.prepare(_ctx(encoder))
    cands = torch.rand(3, 16, 5, generator=torch.Generator().manual_seed(0)) * 2 - 1
    z, spread = dyn.predict(cands)
    za, zb = (m.terminal(cands) for m in dyn.members)
    torch.testing.assert_close(z, (za + zb) / 2)
    torch.testing.assert_close(spread, ((za - zb) / 2).square().flatten(1).mean(1))
    assert spread.min() > 0
    single, _ = learned_dynamics([(a, encoder)])
    assert isinstance(single, LearnedDynamics)


class ForkMember(Dynamics):
    """Toy member: embedding = |s| with s the mean first action dimension, plus ``sign`` * 0.5·relu(s):
    members agree for s < 0 and disagree for s > 0; their mean is |s| either way."""

    def __init__(self, sign):
        self.sign = sign

    @property
    def device(self):
        return torch.device("cpu")

    def covered(self, chunk):
        return chunk

    def terminal(self, actions):  # (B, L, A) -> (B, 1, 1, 1)
        s = actions[:, :, 0].mean(1)  # (B,)
        return (s.abs() + self.sign * 0.5 * s.clamp_min(0)).view(-1, 1, 1, 1)


def _fork_search(weight, seed):
    ens = EnsembleDynamics([ForkMember(+1), ForkMember(-1)])
    pol = PlannedPolicy(EchoWAM(), make_planner("cem", CEMConfig(init_std=0.3)), ens, None, make_cost("patch"),
                        config=PlannedPolicyConfig(disagreement_weight=weight))
    target = torch.full((1, 1, 1), 0.4)  # |s| = 0.4: s = +0.4 and s = -0.4 are equally good for the mean
    res = pol.planner.plan(torch.zeros(16, 5), pol.objective(target), seed=seed)
    return res.mean[:, 0].mean().item()


def test_disagreement_penalty_steers_the_search_away():
    plain = [_fork_search(0.0, s) for s in range(8)]
    careful = [_fork_search(10.0, s) for s in range(8)]
    assert min(plain) < 0 < max(plain)  # without the penalty either side wins
    assert all(s < -0.2 for s in careful), careful  # with it, always the side where the members agree


def test_disagreement_weight_needs_an_ensemble(encoder):
    with pytest.raises(PlanningError, match="ensemble"):
        _policy(encoder, disagreement_weight=1.0)
    with pytest.raises(ValueError, match="warm_start"):
        PlannedPolicyConfig(warm_start="shift")


def test_gate_calibration_reads_seed_costs(tmp_path):
    from wamplan.evaluation.gate import gate_table
    from wamplan.evaluation.records import append_record

    for seed, costs in enumerate([[1.0, 2.0], [3.0, 4.0]]):
        append_record(tmp_path, dict(condition=7, seed=seed, variant="open-loop", planned_chunks=len(costs),
                                     open_loop_chunks={"first-chunk": 1, "gated": 1},
                                     chunks=[dict(planned=True, seed_cost=c) for c in costs]))
    table = gate_table(tmp_path, (0.5,))
    assert table == {7: dict(chunks=4, planned_fraction=4 / 8, quantiles={0.5: 2.5})}
