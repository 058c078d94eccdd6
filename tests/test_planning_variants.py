"""Gated planning and warm starts of the planned policy."""

import numpy as np
import pytest
import torch

from wamplan.planning import CEMConfig, make_cost, make_planner
from wamplan.planning.dynamics import LearnedDynamics
from wamplan.planning.policy import PlannedPolicy, PlannedPolicyConfig
from wamplan.policies.rollout import run_episode
from test_planned_policy import EchoWAM, _predictor, encoder  # noqa: F401 (fixture; small_env is in conftest)


def _cem(n=8, iters=2):
    return make_planner("cem", CEMConfig(num_candidates=n, num_elites=2, iterations=iters))


def _policy(encoder, **cfg):
    return PlannedPolicy(EchoWAM(), _cem(), LearnedDynamics(_predictor(encoder)), encoder, make_cost("patch"),
                         config=PlannedPolicyConfig(**cfg))


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


def test_an_unknown_warm_start_is_refused():
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
