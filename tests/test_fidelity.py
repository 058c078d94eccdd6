"""Planning fidelity: rank statistics, and a run in the real env with the shipped mini models."""

import dataclasses

import numpy as np
import pytest
import torch

from wamplan.planning.dynamics import LearnedDynamics, SimulatorDynamics
from wamplan.evaluation.fidelity import (FidelityConfig, Scored, boundary_stats, cost_slope, format_fidelity, ranks,
                                       run_fidelity, slope_cosine, spearman, top_overlap)
from wamplan.wam import load_wam
from wamplan.worldmodel.load import load_world_model

pytestmark = pytest.mark.usefixtures("one_thread")  # tiny models: one torch thread is faster on a busy 2-core box


def test_rank_statistics():
    a = torch.tensor([0.3, 0.1, 0.2, 0.5])
    assert ranks(torch.tensor([2.0, 1.0, 2.0])).tolist() == [2.5, 1.0, 2.5]
    assert spearman(a, a.exp()) == pytest.approx(1.0) and spearman(a, -a) == pytest.approx(-1.0)
    assert spearman(a, torch.tensor([0.1, 0.3, 0.2, 0.4])) == pytest.approx(0.2)  # d = (2, -2, 0, 0): 1 - 6*8/60
    assert np.isnan(spearman(a, torch.ones(4)))
    assert top_overlap(a, torch.tensor([0.1, 0.3, 0.2, 0.4]), 2) == 0.5
    s = boundary_stats(torch.tensor([0.5, 0.1, 0.2, 0.3]), torch.tensor([2.0, 1.0, 3.0, 4.0]), 2)
    assert s["pick"] == 1 and s["pick_beats_wam"] == 1.0 and s["pick_gain"] == pytest.approx(0.5)
    assert s["random_beats_wam"] == pytest.approx(1 / 3) and s["best_gain"] == pytest.approx(0.5)
    assert np.isnan(s["slope_cosine"])  # no shifts given


def test_slope_agreement():
    g = torch.Generator().manual_seed(0)
    shift = torch.randn(32, 4, generator=g)  # (N, d) end-point shifts
    slope = torch.tensor([1.0, -2.0, 0.5, 0.0])
    true = 3.0 + shift @ slope  # (N,)
    torch.testing.assert_close(cost_slope(true, shift), slope.double(), atol=1e-5, rtol=0)
    noisy = 7.0 + 2.0 * (shift @ slope) + 0.3 * torch.randn(32, generator=g)  # another scale, plus noise: same way
    assert slope_cosine(noisy, true, shift) > 0.95
    assert slope_cosine(-true, true, shift) == pytest.approx(-1.0)
    other = shift @ torch.tensor([0.0, 0.0, 0.0, 1.0])  # a slope along a direction the true cost ignores
    assert abs(slope_cosine(other, true, shift)) < 0.1
    s = boundary_stats(noisy, true, 8, shift)
    assert s["slope_cosine"] == pytest.approx(slope_cosine(noisy, true, shift))
    assert np.isnan(slope_cosine(noisy[:5], true[:5], shift[:5]))  # 5 candidates, 4 slopes + intercept: undetermined


def test_fidelity_of_a_world_model_and_of_the_simulator_against_itself(env):
    """The session env renders at 224 px, what TinyWAM was trained on; 4 candidates, 2 boundaries."""
    wam = load_wam("checkpoints/mini/tinywam", device="cpu")
    model, enc = load_world_model("checkpoints/mini/wm_augmented")
    models = [Scored("augmented", LearnedDynamics(model), enc), Scored("simulator", SimulatorDynamics(env, enc), enc)]
    cfg = FidelityConfig(num_candidates=4, top_k=2, boundaries=(3, 4))  # the cube is held by then: its xy varies
    out = run_fidelity(env, wam, models, [500], cfg)
    recs = out["records"]
    assert [r["step"] for r in recs] == [48, 64]
    for r in recs:
        learned, sim = r["models"]["augmented"], r["models"]["simulator"]
        assert -1 <= learned["spearman"] <= 1 and 0 <= learned["top_overlap"] <= 1
        assert learned["true_costs"] == sim["true_costs"]  # one simulator reference for one encoder
        assert sim["spearman"] == pytest.approx(1.0, abs=1e-9) and sim["top_overlap"] == 1.0
        assert sim["pick_gain"] == pytest.approx(sim["best_gain"])
        assert np.isnan(sim["slope_cosine"])  # 4 candidates cannot determine 4 slopes and an intercept
        assert len(set(learned["model_costs"])) == 4  # four distinct candidates
        assert len(r["task"]["cand_xy_mm"]) == 4 and -1 <= learned["true_vs_xy"] <= 1
    # candidate 0 is the WAM's chunk, which the episode then executed: stepping it from the boundary lands
    # where the episode was at the next boundary (up to PhysX's restore drift, ~1 mm)
    assert recs[0]["task"]["cand_xy_mm"][0] == pytest.approx(recs[1]["task"]["boundary_xy_mm"], abs=2.0)
    s = out["summary"]
    assert s["simulator"]["spearman_median"] == pytest.approx(1.0) and s["augmented"]["boundaries"] == 2
    assert "augmented" in format_fidelity(s, 2)
    # a wrist-only cost (`--cost-view-weights 0 0 1`) scores the same candidates otherwise, in the model and the
    # simulator
    from wamplan.planning.costs import make_cost

    wrist = run_fidelity(env, wam, models, [500], dataclasses.replace(cfg, boundaries=(1,), task_metric=False),
                         cost=make_cost("patch", (0.0, 0.0, 1.0)))["records"][0]["models"]
    assert wrist["augmented"]["model_costs"] != recs[0]["models"]["augmented"]["model_costs"]
    assert wrist["augmented"]["true_costs"] != recs[0]["models"]["augmented"]["true_costs"]
    assert wrist["simulator"]["spearman"] == pytest.approx(1.0, abs=1e-9)


def test_a_twin_with_its_own_view_weights_ranks_and_plans_in_its_cost_and_is_scored_in_the_runs(env):
    """Scored(cost=...) sharing the model's dynamics: the same candidates and simulator (yardstick) costs, its own
    model costs of them, and its own search's plan scored by the simulator after the other model's."""
    from wamplan.planning.costs import make_cost

    wam = load_wam("checkpoints/mini/tinywam", device="cpu")
    model, enc = load_world_model("checkpoints/mini/wm_augmented")
    dyn = LearnedDynamics(model)
    models = [Scored("augmented", dyn, enc), Scored("augmented+views", dyn, enc, cost=make_cost("patch", (1, 1, 0.25)))]
    cfg = FidelityConfig(num_candidates=4, top_k=2, boundaries=(3,), plan=True)
    rec = run_fidelity(env, wam, models, [502], cfg)["records"][0]
    plain, viewed = rec["models"]["augmented"], rec["models"]["augmented+views"]
    assert plain["true_costs"] == viewed["true_costs"] and plain["model_costs"] != pytest.approx(viewed["model_costs"])
    assert len(rec["task"]["cand_xy_mm"]) == 4 + 2 and viewed["plan_gain"] != pytest.approx(plain["plan_gain"])


def test_fidelity_cli_refuses_labels_that_collide_before_loading_anything(capsys):
    from wamplan.cli import main

    wm = "checkpoints/mini/wm_augmented"
    base = ["wm", "fidelity", "--wam", "checkpoints/mini/tinywam", "--seeds", "500"]
    assert main(base + ["--wm", f"a={wm},a=/no/such/dir"]) == 2  # the label is checked before the paths
    assert "a appears twice" in capsys.readouterr().err
    assert main(base + ["--wm", f"x={wm},x+views={wm}", "--plan-view-weights", "1", "1", "0.5"]) == 2
    assert "x+views appears twice" in capsys.readouterr().err
    assert main(base + ["--wm", "x=/no/such/dir", "--plan-view-weights", "1", "-1", "1"]) == 2
    assert "--plan-view-weights 1 -1 1: give weights >= 0 with a positive sum" in capsys.readouterr().err
    assert main(base + ["--wm", f"x={wm}", "--plan-view-weights", "1", "1"]) == 2  # before the episodes run
    assert "--plan-view-weights has 2 weights for the task's 3 cameras ['front', 'side', 'wrist']" in \
        capsys.readouterr().err
    assert main(base + ["--wm", f"x={wm}", "--cost-view-weights", "0", "0", "0"]) == 2  # before anything loads
    assert "--cost-view-weights 0 0 0: give weights >= 0 with a positive sum" in capsys.readouterr().err
    assert main(base + ["--wm", f"x={wm}", "--cost-view-weights", "1", "1"]) == 2
    assert "--cost-view-weights has 2 weights for the task's 3 cameras" in capsys.readouterr().err


@pytest.fixture(scope="module")
def short_env():
    """The cube task cut at 64 steps, one chunk past the last scored boundary's: an executed closed loop ends there
    whatever its outcome (a failing one would otherwise plan every chunk to step 300)."""
    from wamplan.envs.config import EnvConfig
    from wamplan.envs.core import TaskEnv

    e = TaskEnv(EnvConfig(max_episode_steps=64))
    yield e
    e.close()


def test_each_models_own_plan_is_scored_and_one_model_can_drive_the_episode(short_env):
    """plan=True runs each model's search at the scored boundaries without changing the states (the WAM's chunks
    still run); execute=LABEL runs that model's plans to the episode's end, so later boundaries are other states."""
    env = short_env
    wam = load_wam("checkpoints/mini/tinywam", device="cpu")
    model, enc = load_world_model("checkpoints/mini/wm_augmented")
    models = [Scored("augmented", LearnedDynamics(model), enc)]
    plain_model, plain_enc = load_world_model("checkpoints/mini/wm_plain")
    two = [*models, Scored("plain", LearnedDynamics(plain_model), plain_enc)]
    cfg = FidelityConfig(num_candidates=4, top_k=2, boundaries=(2, 3))
    plain = run_fidelity(env, wam, models, [500], cfg)
    planned = run_fidelity(env, wam, two, [500], dataclasses.replace(cfg, plan=True))
    for a, b in zip(plain["records"], planned["records"]):
        assert b["models"]["augmented"]["model_costs"] == pytest.approx(a["models"]["augmented"]["model_costs"])
        assert "plan_gain" not in a["models"]["augmented"]
        row = b["models"]["augmented"]
        true = b["models"]["augmented"]["true_costs"]  # the simulator's costs of the 4 candidates; 0: the WAM's
        assert row["plan_gain"] > -1 and row["plan_gain"] != pytest.approx(0.0)  # a searched plan, not the WAM's chunk
        assert row["plan_gain"] != pytest.approx((true[0] - min(true)) / true[0])  # not one of the fixed candidates
        xy = b["task"]["cand_xy_mm"]
        assert len(xy) == 4 + 2  # the 4 candidates, then each model's plan in the order of the models
        assert row["plan_xy_change_mm"] == pytest.approx(xy[4] - xy[0])
        assert b["models"]["plain"]["plan_xy_change_mm"] == pytest.approx(xy[5] - xy[0])
    s = planned["summary"]["augmented"]
    assert s["plans"] == 2 and s["plan_gain_mean"] == pytest.approx(
        np.mean([r["models"]["augmented"]["plan_gain"] for r in planned["records"]]))
    assert "its own search's plan" in format_fidelity(planned["summary"], 2)
    assert plain["episodes"][0]["length"] == 3 * 16 + 1  # open loop: stopped after the last scored boundary
    # one model drives the episode with its plans while the other searches from the states they lead to
    driven = run_fidelity(env, wam, two, [500], dataclasses.replace(cfg, execute="augmented", plan=True))
    ep = driven["episodes"][0]
    assert ep["success"] or ep["length"] == env.max_episode_steps  # its closed loop, to the end
    assert ep["length"] > 3 * 16 + 1
    rec = driven["records"][0]
    first = rec["models"]["augmented"]
    assert "plan_gain" in first and "plan_gain" in rec["models"]["plain"]  # the executed plan and the other's search
    xy = rec["task"]["cand_xy_mm"]
    assert len(xy) == 4 + 2  # the 4 candidates, the executed plan, the other model's plan
    assert first["plan_xy_change_mm"] == pytest.approx(xy[4] - xy[0])
    assert rec["models"]["plain"]["plan_xy_change_mm"] == pytest.approx(xy[5] - xy[0])
    # boundary 2 follows a planned chunk from boundary 1: the state differs from the open-loop episode's
    assert first["model_costs"] != pytest.approx(plain["records"][0]["models"]["augmented"]["model_costs"])
    from wamplan.planning.policy import PlannedPolicyConfig

    gated = [*models, Scored("gated", models[0].dynamics, enc, PlannedPolicyConfig(gate_threshold=float("inf")))]
    with pytest.raises(ValueError, match="'gated' would record another chunk"):  # its history would lie
        run_fidelity(env, wam, gated, [500], dataclasses.replace(cfg, execute="augmented"))
    with pytest.raises(ValueError, match="names no scored model"):
        run_fidelity(env, wam, models, [500], dataclasses.replace(cfg, execute="other"))


def test_fidelity_cli_checks_execute_and_oracle_blend_before_loading(capsys):
    from wamplan.cli import main

    base = ["wm", "fidelity", "--wam", "checkpoints/mini/tinywam", "--seeds", "500", "--wm", "a=/no/such/dir"]
    assert main(base + ["--execute", "b"]) == 2
    assert "--execute b names no --wm model" in capsys.readouterr().err
    assert main(base + ["--oracle-blend", "1.5"]) == 2
    assert "--oracle-blend 1.5 is outside (0, 1]" in capsys.readouterr().err


def test_fidelity_refuses_an_ensemble_in_one_line(refused):
    """A+B (an ensemble, which left the core) is refused before anything loads; commas still separate models."""
    aug, plain = "checkpoints/mini/wm_augmented", "checkpoints/mini/wm_plain"
    refused(["wm", "fidelity", "--wam", "checkpoints/mini/tinywam", "--wm", f"x={aug}+{plain}", "--seeds", "500"],
            f"--wm {aug}+{plain} joins 2 world models into an ensemble", f"pass one checkpoint, e.g. --wm {aug}")


def test_the_summary_pairs_each_models_plan_gain_with_the_first_models():
    from wamplan.evaluation.fidelity import summarize

    def row(gain):
        return dict(spearman=0.5, top_overlap=0.5, pick_beats_wam=1.0, random_beats_wam=0.5, pick_gain=0.0,
                    best_gain=0.1, true_spread=0.1, slope_cosine=0.5, plan_gain=gain, plan_beats_wam=float(gain > 0),
                    plan_gain_ref=gain)

    gains = [(0.02, 0.05), (0.04, 0.05), (-0.01, 0.03)]  # (first, second) at three boundaries
    recs = [dict(seed=0, step=16 * (i + 1), models=dict(a=row(a), b=row(b))) for i, (a, b) in enumerate(gains)]
    s = summarize(recs, ["a", "b"], FidelityConfig(num_candidates=4, top_k=2))
    d = np.array([b - a for a, b in gains])
    assert s["b"]["plan_gain_ref_vs_first_mean"] == pytest.approx(d.mean())
    assert s["b"]["plan_gain_ref_vs_first_se"] == pytest.approx(d.std(ddof=1) / np.sqrt(3))
    assert "plan_gain_ref_vs_first_mean" not in s["a"] and s["a"]["plan_beats_wam"] == pytest.approx(2 / 3)
    assert "minus the first model's" in format_fidelity(s, 2)
