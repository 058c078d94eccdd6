"""Evaluation records (append, torn-line repair), conditions parsing, Table 1 / Figure 3 / Table 2."""

import json

import numpy as np
import pytest

from wamplan.cli import main
from wamplan.errors import UserError
from wamplan.evaluation.conditions import CONDITIONS, parse_conditions
from wamplan.evaluation.records import RECORDS, append_record, read_records
from wamplan.evaluation.report import (gap_closed, markdown_gap, markdown_paired, markdown_release, sign_test, table1,
                                       wilson)


def test_conditions_match_the_paper():
    assert [(c.dynamics, c.seed, c.target) for c in CONDITIONS.values()] == [
        ("none", "wam", "none"), ("simulator", "expert", "expert"), ("simulator", "expert", "wam"),
        ("simulator", "wam", "expert"), ("simulator", "wam", "wam"), ("learned-plain", "wam", "wam"),
        ("learned-augmented", "wam", "wam")]
    assert parse_conditions("1,6,7") == [1, 6, 7] and parse_conditions("1-7") == list(range(1, 8))
    with pytest.raises(UserError, match="unknown condition"):
        parse_conditions("1,9")
    with pytest.raises(UserError, match="not a list"):
        parse_conditions("one")


def _rec(c, s, outcome, length=120, variant="open-loop", timing=None):
    return dict(condition=c, seed=s, variant=variant, success=outcome == "success", outcome=outcome, length=length,
                chunk_timing_s=timing or {})


def test_paired_comparison_counts_discordant_seeds():
    reached = lambda o: {"aligned": o in ("success", "aligned_not_descended")}  # noqa: E731
    base = ["success", "aligned_not_descended", "never_lifted", "never_lifted", "success"]
    other = ["success", "success", "success", "never_lifted", "aligned_not_descended"]
    recs = [dict(_rec(1, s, o), reached=reached(o)) for s, o in enumerate(base)]
    recs += [dict(_rec(7, s, o), reached=reached(o)) for s, o in enumerate(other)]
    recs.append(dict(_rec(7, 99, "success"), reached=reached("success")))  # a seed the baseline lacks: ignored
    row = markdown_paired(recs).splitlines()[-1]
    # seed 1 and 2 gained, seed 4 lost; p = 2 * (1 + 3) / 8 = 1.0; aligned: base 3 (2 seated), cond 7 4 (3 seated)
    assert row == "| 7 | 5 | 2 | 1 | 1.00 | 67% of 3 → 75% of 4 |"
    assert markdown_paired([r for r in recs if r["condition"] == 1]) is None


def test_records_survive_a_torn_last_line(tmp_path):
    append_record(tmp_path, _rec(1, 0, "success"))
    append_record(tmp_path, _rec(1, 1, "never_lifted"))
    with open(tmp_path / RECORDS, "a") as f:
        f.write('{"condition": 1, "seed": 2, "succ')  # a kill mid-write
    assert [r["seed"] for r in read_records(tmp_path)] == [0, 1]
    read_records(tmp_path, repair=True)
    append_record(tmp_path, _rec(1, 2, "success"))
    assert [r["seed"] for r in read_records(tmp_path)] == [0, 1, 2]
    # a complete record whose newline was lost is kept, and the file is mended
    with open(tmp_path / RECORDS, "a") as f:
        f.write(json.dumps(_rec(1, 3, "success")))
    assert len(read_records(tmp_path, repair=True)) == 4
    append_record(tmp_path, _rec(1, 4, "success"))
    assert [r["seed"] for r in read_records(tmp_path)] == [0, 1, 2, 3, 4]


@pytest.mark.parametrize("line", ['[1, 2]', '{"seed": 3}', '{"condition": "7", "seed": 3}', '{"condition": true, '
                                  '"seed": 3}', '\udcff'])
def test_a_line_that_is_not_an_episode_record_is_named(tmp_path, line):
    from wamplan.errors import UserError

    append_record(tmp_path, _rec(1, 0, "success"))
    with open(tmp_path / RECORDS, "a", errors="surrogateescape") as f:
        f.write(line + "\n")  # a hand-written or foreign line (or bytes that are not UTF-8), complete, not the last
    append_record(tmp_path, _rec(1, 1, "success"))
    with pytest.raises(UserError, match=r"line 2 is damaged or not an episode record .*'condition' and 'seed'"):
        read_records(tmp_path)
    # as the file's last line, without its newline, it is complete, not torn: named too, and left as it was
    if line.isascii():
        (tmp_path / RECORDS).write_text(json.dumps(_rec(1, 0, "success")) + "\n" + line)
        with pytest.raises(UserError, match="line 2 is damaged or not an episode record"):
            read_records(tmp_path, repair=True)
        assert (tmp_path / RECORDS).read_text().endswith("\n" + line)


def test_sign_test_exact_values():
    # exact two-sided binomial test, p = 2 * P(X <= min) under Bin(n, 1/2), worked by hand:
    assert sign_test(6, 0) == pytest.approx(2 / 2 ** 6)  # 0.03125
    assert sign_test(0, 6) == pytest.approx(0.03125)  # symmetric in gained / lost
    assert sign_test(8, 2) == pytest.approx(2 * (1 + 10 + 45) / 2 ** 10)  # 0.109375
    assert sign_test(2, 8) == pytest.approx(0.109375)
    assert sign_test(10, 0) == pytest.approx(2 / 1024)
    assert sign_test(3, 1) == pytest.approx(2 * (1 + 4) / 16)  # 0.625
    assert sign_test(2, 2) == 1.0 and sign_test(0, 0) == 1.0  # clamped, and no discordant pairs
    # and the paired table prints it: 6 seeds gained, none lost
    recs = [_rec(1, s, "never_lifted") for s in range(8)] + [_rec(7, s, "success" if s < 6 else "never_lifted")
                                                              for s in range(8)]
    assert markdown_paired(recs).splitlines()[-1].startswith("| 7 | 8 | 6 | 0 | 0.03 |")


def test_wilson_interval():
    # 95% Wilson score interval (z = 1.959964); reference values computed independently
    # (scipy.stats.binomtest(k, n).proportion_ci(method="wilson")).
    lo, hi = wilson(10, 30)
    assert lo == pytest.approx(0.192305, abs=1e-3) and hi == pytest.approx(0.512199, abs=1e-3)
    lo, hi = wilson(0, 10)
    assert lo == 0.0 and hi == pytest.approx(0.277533, abs=1e-3)
    lo, hi = wilson(17, 50)
    assert lo == pytest.approx(0.224369, abs=1e-3) and hi == pytest.approx(0.478462, abs=1e-3)
    lo, hi = wilson(10, 10)
    assert lo == pytest.approx(1 - 0.277533, abs=1e-3) and hi == 1.0


def test_report_tables_and_figure(tmp_path):
    outcomes = ["success"] * 3 + ["never_lifted", "descended_not_seated"]
    for i, o in enumerate(outcomes):
        append_record(tmp_path, _rec(1, i, o, length=100 + 10 * i))
        append_record(tmp_path, dict(_rec(7, i, "success" if i < 4 else "never_lifted", length=130,
                                          timing={"wam_s": 0.01, "target_encode_s": 0.002, "search_s": 0.5}),
                                     planned_chunks=7, open_loop_chunks={"first-chunk": 1, "warm-up": i % 2}))
        append_record(tmp_path, _rec(7, i, "never_lifted", variant="rest-history"))
    rows = table1(read_records(tmp_path))
    assert [r["condition"] for r in rows] == [1, 7]
    assert rows[0]["success_rate"] == 0.6 and rows[0]["median_length"] == 110 and rows[0]["mean_length"] == 110
    assert rows[1]["mean_search_s"] == 0.5 and rows[1]["outcomes"] == {"success": 4, "never_lifted": 1}
    assert main(["report", str(tmp_path)]) == 0
    md = (tmp_path / "report.md").read_text()
    assert "| 1 | None (open loop) | WAM | — | 5 | 60% (23–88) | 110 | 110 |" in md
    assert "Table 2" in md and "| 7 | planned | 5 | 0% | 100% | 0% |" in md
    # every chunk is accounted for: 35 planned, 5 first chunks and 2 warm-up chunks open loop, none gated
    assert "| 7 | 0.010 | 0.002 | 0.500 | 35 | 5 / 2 / 0 / 0 |" in md
    import imageio.v3 as iio

    assert iio.imread(tmp_path / "figure3.png").shape[2] in (3, 4)
    assert (tmp_path / "table1.csv").read_text().splitlines()[0].startswith("condition,")
    assert "Planner:" not in md  # no eval_config.json here: nothing to say


def test_report_names_the_planner_and_what_was_changed(tmp_path):
    from wamplan.evaluation.config import EvalConfig
    from wamplan.evaluation.runner import _check_same_settings

    append_record(tmp_path, _rec(1, 0, "success"))
    for cfg, line in ((EvalConfig(), "Planner: `wamplan` (32 candidates × 4 iterations; changed from its defaults: none;"),
                      (EvalConfig(planner="cem", planner_config={"num_elites": 4}),
                       "Planner: `cem` (32 candidates × 4 iterations; changed from its defaults: num_elites 4;")):
        (tmp_path / "eval_config.json").unlink(missing_ok=True)
        _check_same_settings(tmp_path, cfg)
        assert main(["report", str(tmp_path)]) == 0
        md = (tmp_path / "report.md").read_text()
        assert line in md and "oracle-blend" not in md
    (tmp_path / "eval_config.json").unlink()
    _check_same_settings(tmp_path, EvalConfig(oracle_blend=0.5))  # the diagnostic says so under the table
    assert main(["report", str(tmp_path)]) == 0
    assert "moved 0.5 of the way to the simulator's (`--oracle-blend`)" in (tmp_path / "report.md").read_text()


def test_eval_needs_its_checkpoints(tmp_path, capsys):
    assert main(["eval", "--conditions", "1", "--episodes", "1", "--out", str(tmp_path)]) == 2
    assert "--wam CKPT is required" in capsys.readouterr().err
    assert main(["eval", "--conditions", "6", "--episodes", "1", "--out", str(tmp_path), "--wam", str(tmp_path)]) == 2
    assert "condition 6 needs --wm-plain" in capsys.readouterr().err
    assert main(["report", str(tmp_path / "nothing")]) == 2
    assert f"{tmp_path / 'nothing'} does not exist; pass an evaluation directory (made by `wamplan eval`)" in \
        capsys.readouterr().err


def test_reproduce_stages_wire_the_pipeline(tmp_path):
    from wamplan.evaluation.reproduce import PRESETS, SEED_BASE, stages

    st = dict(stages(PRESETS["mini"], tmp_path, None, 2))
    names = list(st)
    assert names[:4] == ["collect expert", "collect noisy", "collect pink", "train TinyWAM"]
    assert names.index("collect on-policy") > names.index("train TinyWAM") and names[-1] == "report"
    wam = st["train TinyWAM"][0][st["train TinyWAM"][0].index("--out") + 1]
    on_policy = st["collect on-policy"][0]
    assert on_policy[on_policy.index("--policy") + 1] == wam
    plain = st["train plain world model"][0][3]
    aug = st["train augmented world model"][0][3]
    assert "on_policy" not in plain and aug.startswith(plain) and aug.endswith("on_policy")
    assert min(SEED_BASE.values()) >= PRESETS["paper"].eval_episodes  # training seeds never overlap eval seeds
    ev = st["evaluate"][0]
    assert ev[ev.index("--planner") + 1] == "cem"  # the paper's experiment with the paper's planner
    given = dict(stages(PRESETS["mini"], tmp_path, "/ckpt/wam", 1))
    assert "train TinyWAM" not in given and "/ckpt/wam" in given["evaluate"][0]
    assert not any("--task" in cmd for cmds in st.values() for cmd in cmds)  # the default task: as before tasks
    peg = dict(stages(PRESETS["mini"], tmp_path, None, 1, task="peg-insertion-side"))  # no expert: ManiSkill's demos
    assert list(peg)[:5] == ["demonstrations", "import demonstrations", "import noisy", "collect pink", "train TinyWAM"]
    assert peg["demonstrations"][0][0] == "scripts/maniskill_demos.sh"
    imp, noisy, wam = peg["import demonstrations"][0], peg["import noisy"][0], peg["train TinyWAM"][0]
    assert imp[imp.index("--episodes") + 1] == "100" and "--noise-std" in noisy and "--noise-std" not in imp
    assert wam[wam.index("--sources") + 1] == "demo" and wam[wam.index("--data") + 1] == imp[5]
    assert [cmd[cmd.index("--conditions") + 1] for cmd in peg["evaluate"]] == ["1,6,7", "5"]  # 2-4 need an expert
    assert all(cmd[cmd.index("--task") + 1] == "peg-insertion-side" for cmd in peg["evaluate"])
    assert not any("--camera-size" in cmd for cmds in peg.values() for cmd in cmds)  # the default size: no flag
    small = dict(stages(PRESETS["mini"], tmp_path, None, 1, task="peg-insertion-side", camera_size=128))
    renders = [cmd for cmds in small.values() for cmd in cmds
               if cmd[0] in ("collect", "eval") or cmd[:2] == ["data", "import"]]
    assert renders and all(cmd[cmd.index("--camera-size") + 1] == "128" for cmd in renders)  # every env made: 128 px
    assert not any("--camera-size" in cmd for cmds in small.values() for cmd in cmds if cmd[0] in ("wam", "wm"))
    with pytest.raises(UserError, match="--camera-size"):
        stages(PRESETS["mini"], tmp_path, None, 1, task="peg-insertion-side", camera_size=8)
    from wamplan.envs.maniskill import maniskill_task
    from wamplan.envs.spec import TASKS

    bare = maniskill_task("PickCube-v1", name="no-demos", cameras=("base_camera",), action_dim=7, proprio_dim=16,
                          max_episode_steps=50, instruction="pick")
    dict.__setitem__(TASKS, "no-demos", bare)
    try:
        with pytest.raises(UserError, match="task 'no-demos' has neither a scripted expert nor"):
            stages(PRESETS["mini"], tmp_path, None, 1, task="no-demos")
    finally:
        dict.__delitem__(TASKS, "no-demos")


def test_report_merges_runs_of_different_conditions(tmp_path, capsys):
    """Conditions run apart on the same seeds make one Table 1, Figure 3 and paired comparison."""
    c1, c7, merged = tmp_path / "c1", tmp_path / "c7", tmp_path / "merged"
    c1.mkdir(), c7.mkdir()
    for i in range(6):
        append_record(c1, _rec(1, i, "success" if i < 2 else "aligned_not_descended"))
        append_record(c7, _rec(7, i, "success" if i < 5 else "never_lifted"))
    assert main(["report", str(merged), str(c1), str(c7)]) == 0
    md = (merged / "report.md").read_text()
    assert "| 1 | None (open loop) | WAM | — | 6 | 33% (10–70) |" in md
    assert "| 7 | 6 | 3 | 0 | 0.25 |" in md  # seeds 2-4 gained, none lost
    assert f"`{c1}`" in md and not (c1 / "report.md").exists()
    append_record(merged, _rec(7, 0, "success"))  # the same episode in two runs: refused, nothing written
    (merged / "report.md").unlink()
    assert main(["report", str(merged), str(c7)]) == 2
    assert "condition 7 (open-loop) seed 0 is in both" in capsys.readouterr().err
    assert not (merged / "report.md").exists()
    assert main(["report", str(merged), f"{c1}:1"]) == 0  # only the conditions named: no clash
    assert main(["report", str(merged), f"{c7}:1"]) == 2  # a condition that run does not hold is named
    assert "holds no records of condition(s) [1]" in capsys.readouterr().err
    assert main(["report", str(merged), str(tmp_path / "missing")]) == 2
    assert "has no evaluation records" in capsys.readouterr().err


def test_gap_to_the_oracle_is_measured_on_shared_seeds():
    """Condition 7 closing 3 of the 6 seeds between condition 1 (2/10) and the oracle, condition 5 (8/10)."""
    recs = [_rec(1, s, "success" if s < 2 else "never_lifted") for s in range(10)]
    recs += [_rec(5, s, "success" if s < 8 else "never_lifted") for s in range(10)]
    recs += [_rec(7, s, "success" if s < 5 else "never_lifted") for s in range(10)]
    recs += [_rec(7, 50 + s, "success") for s in range(5)]  # seeds the oracle did not run: left out
    row = markdown_gap(recs).splitlines()[-1]
    assert row.startswith("| 7 | 5 | 10 | 2 / 5 / 8 | 50% (")
    assert row.endswith("| 3 |")  # seeds 5-7: the oracle solves them, condition 7 does not
    point, lo, hi = gap_closed(*(np.array([r["success"] for r in recs if r["condition"] == c and r["seed"] < 10],
                                          dtype=float) for c in (1, 7, 5)))
    assert point == pytest.approx(0.5) and 0.0 <= lo < 0.5 < hi <= 1.0
    assert markdown_gap([r for r in recs if r["condition"] != 5]) is None  # no oracle run: no row
    flat = [_rec(c, s, "never_lifted") for c in (1, 5, 7) for s in range(4)]
    assert "no gap" in markdown_gap(flat)


def test_gap_interval_is_pinned_on_a_fixed_table():
    """The 95 % percentile bootstrap of the gap closed, on 24 fixed seeds (per seed: baseline, this, oracle):
    3 solved by all, 9 gained by this and the oracle, 1 by this alone, 7 by the oracle alone, 4 by none. The
    numbers pin the estimator (2000 resamples over seeds from seed 0, resamples without a gap left out, the
    2.5 % and 97.5 % quantiles); an independent loop over the same resamples must agree."""
    t = np.array([[1, 1, 1]] * 3 + [[0, 1, 1]] * 9 + [[0, 1, 0]] + [[0, 0, 1]] * 7 + [[0, 0, 0]] * 4, float)
    base, this, ceil = t.T  # (24,) each: 3 / 13 / 19 successes
    point, lo, hi = gap_closed(base, this, ceil)
    assert point == pytest.approx(10 / 16)
    assert (lo, hi) == (pytest.approx(0.3570378, abs=1e-6), pytest.approx(0.9285714, abs=1e-6))
    ratios = []
    for idx in np.random.default_rng(0).integers(0, 24, size=(2000, 24)):
        gap = ceil[idx].mean() - base[idx].mean()
        if gap > 0:
            ratios.append((this[idx].mean() - base[idx].mean()) / gap)
    assert (lo, hi) == (pytest.approx(np.quantile(ratios, 0.025)), pytest.approx(np.quantile(ratios, 0.975)))
    recs = [_rec(c, s, "success" if row[k] else "never_lifted") for s, row in enumerate(t)
            for k, c in enumerate((1, 7, 5))]
    assert markdown_gap(recs).splitlines()[-1] == "| 7 | 5 | 24 | 3 / 13 / 19 | 62% (36–93) | 7 |"


def test_release_table_counts_where_each_condition_let_go():
    rel = lambda xy, bottom: dict(t=140, xy_mm=xy + 1, bottom_mm=0.0, grasped=False, held_mm=[xy, bottom])  # noqa: E731
    recs = [dict(_rec(1, 0, "success"), release=rel(1.0, 20.0)), dict(_rec(1, 1, "success"), release=rel(3.0, 22.0)),
            dict(_rec(1, 2, "success"), release=None, held_at_end=True),
            dict(_rec(1, 3, "never_lifted")),  # written before the trace: not counted
            dict(_rec(7, 0, "success"), release=rel(2.0, 21.0)),
            dict(_rec(7, 1, "descended_not_seated"), release=rel(8.0, 44.0)),
            dict(_rec(7, 2, "lifted_not_aligned"), release=rel(6.0, 40.0))]
    lines = markdown_release(recs).splitlines()
    assert lines[2] == "| 1 | 3 | 2 | 1 | 2.0 [1.5, 2.5] | 21.0 | 2 | 2 of 2 / 0 of 0 |"  # where it was last held
    assert lines[3] == "| 7 | 3 | 3 | 0 | 6.0 [4.0, 7.0] | 40.0 | 1 | 1 of 1 / 0 of 2 |"
    assert markdown_release([_rec(1, 0, "success")]) is None  # records from before the trace: no table


def test_the_release_is_the_final_let_go_of_a_lifted_cube():
    """A graze at the start (grasped, never lifted) is no release; the last let-go after a lift is; a cube
    held again at the end has none."""
    from types import SimpleNamespace

    from wamplan.evaluation.trace import CubeTrace

    def feed(trace, t, grasped, bottom, xy=0.05):
        env = SimpleNamespace(metrics=dict(cube_xy_error=xy, cube_bottom=bottom, cube_tilt=0.0, cube_yaw_error=0.0,
                                           grasped=grasped, lifted=bottom > 0.01))
        trace(env, SimpleNamespace(step=t, proprio=np.zeros(10, np.float32)), None)

    path = [(True, 0.0), (False, 0.0), (True, 0.0), (True, 0.03), (False, 0.028), (True, 0.03), (True, 0.045),
            (False, 0.044)]  # graze, grasp, lift, drop, regrasp, carry, let go
    trace = CubeTrace(every=2)
    for t, (g, b) in enumerate(path):
        feed(trace, t, g, b, xy=0.01 * t)
    assert trace.releases == 2 and not trace.held_at_end
    assert trace.release["t"] == 7 and trace.release["held_mm"] == [60.0, 45.0]
    assert [r["t"] for r in trace.close()] == [0, 2, 4, 6, 7]
    feed(trace, 8, True, 0.045)  # grasped again at the end: nothing was let go for good
    assert trace.release is None and trace.summary()["held_at_end"]


def test_a_blended_run_is_labelled_as_such_in_table1():
    """Records of the --oracle-blend diagnostic carry its weight; Table 1 (and Figure 3) name the blend."""
    rows = table1([_rec(1, 0, "success"), dict(_rec(7, 0, "success"), oracle_blend=0.25)])
    assert [r["dynamics"] for r in rows] == ["None (open loop)", "Augmented WM 0.75 + simulator 0.25"]
    assert table1([_rec(7, 0, "success")])[0]["dynamics"] == "Augmented WM"


def test_the_report_of_a_task_without_stages_leaves_the_cube_readings_out(tmp_path, capsys):
    """push-cube has no stages, metrics or alignment tolerance: its outcomes are success and failure, and the
    insertion columns and the release table are left out; runs of two tasks are not merged."""
    from wamplan.envs.config import EnvConfig
    from wamplan.envs.spec import get_task
    from wamplan.evaluation.config import EvalConfig
    from wamplan.evaluation.report import markdown_table2, outcome_colors
    from wamplan.evaluation.runner import _check_same_settings

    push = get_task("push-cube")
    assert outcome_colors(push) == {"success": "#2e7d32", "failure": "#d32f2f"}
    assert list(outcome_colors(get_task("cube-insertion"))) == ["success", "never_lifted", "lifted_not_aligned",
                                                                "aligned_not_descended", "descended_not_seated"]
    run = tmp_path / "push"
    run.mkdir()
    _check_same_settings(run, EvalConfig(env=EnvConfig(task="push-cube")))
    for s in range(4):
        append_record(run, dict(_rec(1, s, "success" if s < 1 else "failure"), reached={}))
        append_record(run, dict(_rec(7, s, "success" if s < 3 else "failure"), reached={}))
        append_record(run, dict(_rec(7, s, "failure", variant="rest-history"), reached={}))
    assert main(["report", str(run)]) == 0
    md = (run / "report.md").read_text()
    assert "| Condition | First chunk | Episodes | Success | Failure |" in md
    assert "| 7 | planned | 4 | 0% | 100% |" in md
    assert "| 7 | 4 | 2 | 0 | 0.50 |\n" in md + "\n" and "Inserted" not in md and "let go" not in md
    assert (run / "table1.csv").read_text().splitlines()[0].endswith(",success,failure")
    recs = read_records(run)
    assert markdown_release([dict(r, release=None) for r in recs], push) is None  # no tolerance to read against
    assert markdown_table2(recs, push).splitlines()[0].endswith("| Success | Failure |")
    cube = tmp_path / "cube"
    cube.mkdir()
    _check_same_settings(cube, EvalConfig())
    append_record(cube, _rec(1, 9, "success"))
    assert main(["report", str(tmp_path / "both"), str(run), str(cube)]) == 2
    assert "the runs evaluated different tasks" in capsys.readouterr().err


def test_gap_interval_leaves_out_resamples_without_a_gap():
    """On 5 seeds where only seed 0 separates the oracle from the baseline, every resample that misses it (about a
    third) has no gap and no ratio: the interval comes from the resamples that have one (here all 1), never NaN."""
    base, this, ceil = np.zeros(5), np.array([1.0, 0, 0, 0, 0]), np.array([1.0, 0, 0, 0, 0])
    idx = np.random.default_rng(0).integers(0, 5, size=(2000, 5))
    assert 300 < (ceil[idx].mean(-1) <= base[idx].mean(-1)).sum() < 1000  # the table has resamples without a gap
    assert gap_closed(base, this, ceil) == (1.0, 1.0, 1.0)
    this = np.array([1.0, 1, 0, 0, 0])  # seed 1 solved by this alone: the resamples' ratios spread above 1
    point, lo, hi = gap_closed(base, this, ceil)
    gapped = idx[ceil[idx].mean(-1) > 0]
    ratios = this[gapped].mean(-1) / ceil[gapped].mean(-1)
    assert point == 2.0
    assert (lo, hi) == (pytest.approx(np.quantile(ratios, 0.025)), pytest.approx(np.quantile(ratios, 0.975)))
    assert np.isfinite([lo, hi]).all() and lo < hi
