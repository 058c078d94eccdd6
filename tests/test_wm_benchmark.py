"""The offline world-model benchmark (issue 41): phase labels, the benchmark store's command, and `wm eval`'s
per-phase table of sibling statistics, latent errors and planning time."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from wamplan.data.alignment import hole_position
from wamplan.envs.spec import get_task
from wamplan.errors import UserError
from wamplan.worldmodel.benchmark import ALL, PHASES, phase_of

STAGES = get_task("cube-insertion").stages

# the expert (as the policy) on one seed, every boundary branched twice, at 64 px (~20 s)
TINY_STORE = ["--policy", "expert", "--plan-with", "", "--episodes", "1", "--seed-start", "3", "--branches", "2",
              "--max-steps", "160", "--camera-size", "64", "--workers", "1"]


@pytest.fixture(scope="module")
def bench_script(repo_script):
    return repo_script("scripts/wm_benchmark_store.py")


def _flags(*names: str) -> np.ndarray:
    return np.array([s in names for s in STAGES])


def test_phase_of_reads_the_stage_flags_and_whether_the_cube_is_over_the_mount():
    hole, half = hole_position({}), 0.02
    over = np.array([hole[0] + 0.01, hole[1], hole[2] + half + 0.01, 1, 0, 0, 0])  # (7,) 10 mm off the axis, above
    away = np.array([hole[0] + 0.08, hole[1], hole[2] + half + 0.05, 1, 0, 0, 0])
    on_table = np.array([0.05, -0.05, half, 1, 0, 0, 0])
    assert phase_of(_flags(), on_table, hole, half, STAGES) == "grasp"
    assert phase_of(_flags("grasped"), on_table, hole, half, STAGES) == "grasp"  # closing, not yet lifted
    assert phase_of(_flags("grasped", "lifted"), away, hole, half, STAGES) == "carry"
    assert phase_of(_flags("grasped", "lifted"), over, hole, half, STAGES) == "alignment"
    assert phase_of(_flags("grasped", "lifted", "aligned"), over, hole, half, STAGES) == "descent"
    assert phase_of(_flags("grasped", "lifted", "descended"), over, hole, half, STAGES) == "descent"
    low = over.copy()
    low[2] = hole[2] + half - 0.01  # beside the mount, below its top: not over it
    assert phase_of(_flags("grasped", "lifted"), low, hole, half, STAGES) == "carry"


def test_the_phases_are_the_cube_tasks_and_another_task_is_one_line(tmp_path):
    from wamplan.data.store import EpisodeStore
    from wamplan.envs.config import EnvConfig
    from wamplan.worldmodel.benchmark import phase_task_of

    stack = EpisodeStore(tmp_path / "stack", create=True, image_every=4,
                         env=EnvConfig(task="stack-cube", camera_size=64).task_kwargs())
    with pytest.raises(UserError, match="defined for task cube-insertion") as e:
        phase_task_of(stack)
    assert "stack-cube" in str(e.value) and "\n" not in str(e.value)
    cube = EpisodeStore(tmp_path / "cube", create=True, image_every=4, env=EnvConfig(camera_size=64).task_kwargs())
    assert phase_task_of(cube).stages == STAGES


@pytest.fixture(scope="module")
def bench_store(tmp_path_factory, bench_script) -> tuple[Path, dict]:
    """A tiny benchmark-style store made by the benchmark's script (another policy and size: not the benchmark)."""
    out = tmp_path_factory.mktemp("bench") / "store"
    mod = bench_script
    assert mod.main(["--out", str(out), *TINY_STORE]) == 0
    return out, mod


def test_the_benchmark_command_is_the_documented_one_and_labels_the_phases(bench_store, capsys):
    out, mod = bench_store
    argv = mod.collect_argv("DIR", 2, mod.BENCHMARK)
    doc = " ".join(mod.__doc__.split())
    assert " ".join(["wamplan", *argv[:-1]]) + " W" in doc  # the docstring states the exact command
    assert mod.main(["--out", str(out), "--check", *TINY_STORE]) == 0
    report = json.loads(capsys.readouterr().out.split("\n", 1)[1])  # after the "NOT the benchmark store" line
    assert not report["benchmark"] and report["episodes"] > 1
    groups = report["groups"]
    assert groups["siblings"] == 2 and groups[ALL] == sum(groups[p] for p in PHASES)
    # the expert's boundaries 16..144: on the table, carried, then (aligned within one chunk) the descent
    assert (groups["grasp"], groups["carry"], groups["alignment"], groups["descent"]) == (3, 3, 0, 3), groups
    from wamplan.data.readers import BranchGroups
    from wamplan.worldmodel.benchmark import group_phases

    branched = BranchGroups([out], 4, 3, 4, split="all")
    labels = group_phases(branched)  # groups sorted by boundary: the phases come in the task's order
    assert [PHASES.index(p) for p in labels] == sorted(PHASES.index(p) for p in labels)
    assert [branched.episodes[m[0][0]].branch_at[0] for m in branched.items] == list(range(16, 145, 16))


def test_collection_is_deterministic(tmp_path, bench_script):
    """Two collections with the same settings record the same trajectories (the script's fingerprint)."""
    from wamplan.worldmodel.benchmark import store_fingerprint

    mod = bench_script
    short = [a if a != "160" else "56" for a in TINY_STORE]  # boundaries 16 and 32 only
    for run in ("a", "b"):
        assert mod.main(["--out", str(tmp_path / run), *short]) == 0
    fa, fb = store_fingerprint(tmp_path / "a"), store_fingerprint(tmp_path / "b")
    assert fa == fb and len(fa) == 40


def test_wm_eval_prints_the_per_phase_table(bench_store, tmp_path, capsys):
    from wamplan.cli import main
    from wamplan.data.features import feature_key
    from wamplan.data.readers import BranchGroups
    from wamplan.worldmodel.benchmark import group_phases, phase_table
    from wamplan.worldmodel.load import load_world_model
    from wamplan.worldmodel.siblings import evaluate_siblings

    out, _ = bench_store
    run = tmp_path / "wm"
    assert main(["wm", "train", "--data", str(out), "--out", str(run), "--max-steps", "2", "--batch-size", "4",
                 "--depth", "1", "--action-conditioning", "adaln", "--action-tokens"]) == 0
    capsys.readouterr()
    assert main(["wm", "eval", "--ckpt", str(run / "checkpoint"), "--data", str(out), "--split", "all",
                 "--json", str(tmp_path / "eval.json")]) == 0
    text = capsys.readouterr().out
    scored = json.loads((tmp_path / "eval.json").read_text())
    table = scored["phases"]
    assert list(table) == ["grasp", "carry", "descent", ALL] and scored["plan_s_per_chunk"] > 0  # no alignment groups
    head = next(line for line in text.splitlines() if line.startswith("phase"))
    assert all(c in head for c in ("sib_rel_h4", "sib_gain_h4", "z_mse_h1", "z_mse_h4", "plan s/chunk"))
    rows = {line.split()[0]: line.split()[1:] for line in text.splitlines() if line.split()[:1] in ([p] for p in table)}
    assert set(rows) == set(table) and float(rows[ALL][-1]) == pytest.approx(scored["plan_s_per_chunk"], abs=1e-3)
    assert int(rows["descent"][0]) == table["descent"]["groups"] == 3
    # the "all" row is `wm eval`'s pooled sibling statistics, and the phases' groups add up to it
    assert table[ALL]["sib_rel_h4"] == pytest.approx(scored["sib_rel_h4"], rel=1e-6)
    assert table[ALL]["sib_gain_h4"] == pytest.approx(scored["sib_gain_h4"], rel=1e-6, abs=1e-9)
    assert table[ALL]["groups"] == scored["sibling_groups"] == sum(table[p]["groups"] for p in table if p != ALL)
    model, enc = load_world_model(run / "checkpoint")
    assert model.cfg.action_conditioning == "adaln" and model.cfg.action_tokens and model.cfg.depth == 1
    groups = BranchGroups([out], 4, 3, 4, split="all", features=feature_key(enc.config_dict()))
    labels = group_phases(groups)
    pooled = evaluate_siblings(model, groups, 4)  # the "all" row is this, computed once by `wm eval`
    assert {k: table[ALL][k] for k in pooled} == pytest.approx(pooled, rel=1e-6, abs=1e-9)
    with torch.no_grad():
        for phase in ("grasp", "carry", "descent"):  # a phase's row is the plain statistics of its groups alone
            mine = [groups[i] for i, p in enumerate(labels) if p == phase]
            alone = evaluate_siblings(model, mine, 4)
            assert table[phase]["sib_rel_h4"] == pytest.approx(alone["sib_rel_h4"], rel=1e-5)
    with pytest.raises(ValueError, match="phase labels"):
        phase_table(model, groups, 4, phases=labels[:-1])
