"""lab/tools/fidelity_table.py: fidelity JSON files of split seeds merged into one paired table."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


@pytest.fixture(scope="module")
def table(repo_script):
    return repo_script("lab/tools/fidelity_table.py")


def _row(gain: float) -> dict:
    return dict(spearman=0.5, top_overlap=0.5, pick_beats_wam=1.0, random_beats_wam=0.5, pick_gain=0.0, best_gain=0.1,
                true_spread=0.1, slope_cosine=0.5, plan_gain=gain, plan_beats_wam=float(gain > 0), plan_gain_ref=gain,
                plan_xy_change_mm=-100 * gain)


def _write(path: Path, seed: int, gains: list[tuple[float, float]], labels=("a", "b")) -> Path:
    recs = [dict(seed=seed, step=16 * (i + 1), models={labels[0]: _row(x), labels[1]: _row(y)})
            for i, (x, y) in enumerate(gains)]
    path.write_text(json.dumps(dict(records=recs, config=dict(num_candidates=4, top_k=2, boundaries=[1, 2]))))
    return path


def test_split_runs_merge_into_one_paired_row(table, tmp_path, capsys):
    one = _write(tmp_path / "one.json", 500, [(0.02, 0.05), (0.04, 0.05)])
    two = _write(tmp_path / "two.json", 501, [(-0.01, 0.03), (0.00, 0.04)])
    assert table.main([str(one), str(two), "--markdown"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("4 boundaries, seeds 500-501 (2)")
    row = next(line for line in out.splitlines() if line.startswith("| b |"))
    assert "+3.00 ± 0.71" in row  # the paired differences 3, 1, 4, 4 points: mean 3, SD 1.41, SE 0.71
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[-3] == "+4.25 / +10.00"  # own cost: b's plan gains 5, 5, 3, 4 %; the best candidate 10 % each
    assert cells[-2] == "-3.00 ± 0.71"  # cube xy: -100 x gain, so 3 mm nearer on average, paired as the gain
    assert cells[-1] == "+3.50, 4-0 (p = 0.125)"  # differences 3, 1, 4, 4: median 3.5, above at all 4 boundaries


def test_overlapping_or_mismatched_files_are_one_line(table, tmp_path):
    one = _write(tmp_path / "one.json", 500, [(0.02, 0.05)])
    with pytest.raises(SystemExit, match="seed 500 step 16 is in two files"):
        table.main([str(one), str(one)])
    other = _write(tmp_path / "other.json", 501, [(0.02, 0.05)], labels=("a", "c"))
    with pytest.raises(SystemExit, match="scores models"):
        table.main([str(one), str(other)])
    closed = _write(tmp_path / "closed.json", 502, [(0.02, 0.05)])
    cfg = json.loads(closed.read_text())
    cfg["config"]["execute"] = "a"
    closed.write_text(json.dumps(cfg))
    with pytest.raises(SystemExit, match="open-loop and closed-loop states do not pool"):
        table.main([str(one), str(closed)])
    with pytest.raises(SystemExit, match="does not exist"):
        table.main([str(tmp_path / "none.json")])


def test_the_plot_draws_the_named_models_and_refuses_unknown_ones(table, tmp_path, capsys):
    one = _write(tmp_path / "one.json", 500, [(0.02, 0.05), (0.04, 0.05)])
    assert table.main([str(one), "--plot", str(tmp_path / "g.png")]) == 0
    assert (tmp_path / "g.png").stat().st_size > 0 and "wrote" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="--models z not among"):
        table.main([str(one), "--plot", str(tmp_path / "h.png"), "--models", "b,z"])


def test_steps_keep_one_phase_and_name_the_steps_there_are(table, tmp_path, capsys):
    one = _write(tmp_path / "one.json", 500, [(0.02, 0.05), (0.04, 0.05), (0.00, 0.10)])
    assert table.main([str(one), "--steps", "32-48", "--markdown"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("2 boundaries, seeds 500-500 (1), steps [32, 48]")
    row = next(line for line in out.splitlines() if line.startswith("| b |"))
    assert "+5.50 ± 4.50" in row  # steps 32 and 48: differences 1 and 10 points
    with pytest.raises(SystemExit, match=r"no scored boundary lies at --steps 64; the files hold steps \[16, 32, 48\]"):
        table.main([str(one), "--steps", "64"])
    with pytest.raises(SystemExit, match="--steps 'x' is not a list"):
        table.main([str(one), "--steps", "x"])
