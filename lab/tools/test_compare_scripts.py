"""``lab/tools/compare_runs.py`` (two evaluation directories paired seed by seed) and ``lab/tools/fidelity_pair.py``
(two fidelity runs paired boundary by boundary)."""

from __future__ import annotations

import json

import pytest

from wamplan.evaluation.records import append_record


def _run(path, outcomes: dict[int, str], search: float = 1.0):
    path.mkdir()
    for seed, outcome in outcomes.items():
        append_record(path, {"condition": 7, "seed": seed, "success": outcome == "success", "outcome": outcome,
                             "chunks": [{"planned": True, "search_s": search}, {"planned": False}]})
    append_record(path, {"condition": 1, "seed": 0, "success": True, "outcome": "success"})  # another condition
    return path


def test_compare_runs_pairs_seeds_and_counts_what_moved(tmp_path, repo_script):
    cmp = repo_script("lab/tools/compare_runs.py")
    a = _run(tmp_path / "a", {0: "success", 1: "success", 2: "lifted_not_aligned", 3: "success", 9: "success"},
             search=0.5)
    b = _run(tmp_path / "b", {0: "success", 1: "descended_not_seated", 2: "success", 3: "descended_not_seated"})
    r = cmp.compare(cmp.by_seed(a, 7), cmp.by_seed(b, 7))
    assert r["seeds"] == 4  # seed 9 is A's alone
    assert [run["success"] for run in r["runs"]] == [3, 2] and (r["gained"], r["lost"]) == (2, 1)
    assert r["p"] == pytest.approx(1.0) and r["runs"][0]["search_s"] == 0.5  # the unplanned chunk does not count
    assert dict(r["moves"]) == {("descended_not_seated", "success"): 2, ("success", "lifted_not_aligned"): 1}
    with pytest.raises(SystemExit, match="no finished episode of condition 6"):
        cmp.by_seed(a, 6)


def _fidelity(path, picks, spearman):
    records = [{"seed": 500, "step": 16 * (i + 2), "models": {"shipped": {
        "spearman": s, "top_overlap": 0.5, "pick_gain": 0.01, "pick": p, "true_costs": [1, 2, 3, 4 + i],
        "model_costs": [1, 3, 2, 4]}}} for i, (p, s) in enumerate(zip(picks, spearman))]
    path.write_text(json.dumps({"records": records, "summary": {}}))
    return str(path)


def test_fidelity_pair_pairs_boundaries(tmp_path, repo_script):
    fp = repo_script("lab/tools/fidelity_pair.py")
    a = fp.boundaries(_fidelity(tmp_path / "a.json", [0, 1, 2], [0.5, 0.6, 0.7]), "shipped")
    b = fp.boundaries(_fidelity(tmp_path / "b.json", [0, 1, 3], [0.6, 0.7, 0.8]), "shipped")
    r = fp.pair(a, b)
    assert r["boundaries"] == 3 and r["spearman"][0] == pytest.approx(0.1) and r["spearman"][1] == pytest.approx(0)
    assert r["same_pick"] == pytest.approx(2 / 3) and r["true_alike"] == pytest.approx(1.0)
    with pytest.raises(SystemExit, match="scores no boundary of model 'other'"):
        fp.boundaries(str(tmp_path / "a.json"), "other")


def test_a_scripts_bad_input_is_one_line_and_status_2(tmp_path, capsys):
    from wamplan.errors import UserError, run_script

    def main():
        raise UserError("--seeds 0-: give a range like 500-503")

    with pytest.raises(SystemExit) as stop:
        run_script(main, "probe")
    assert stop.value.code == 2 and capsys.readouterr().err == "probe: error: --seeds 0-: give a range like 500-503\n"
    run_script(lambda: None, "probe")  # a good run returns
