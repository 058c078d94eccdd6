"""Tiny end to end: collect 2 episodes -> train TinyWAM and the world model a few steps -> evaluate
conditions 1 and 6 (one planned chunk) -> resume -> report. Catches wiring breaks, not quality."""

import json
import math
import shutil

import pytest
import torch

from wamplan.cli import main
from wamplan.evaluation.records import read_records


@pytest.fixture(scope="module")
def run(tmp_path_factory, expert_store):
    root = tmp_path_factory.mktemp("e2e")
    store = shutil.copytree(expert_store, root / "expert")  # a copy: `wm train` caches features in the store
    assert main(["wam", "train", "--data", str(store), "--out", str(root / "wam"), "--epochs", "1", "--max-steps", "3",
                 "--batch-size", "8", "--channels", "8", "16", "--latent-dim", "32", "--trunk-dim", "64",
                 "--no-progress"]) == 0
    assert main(["wm", "train", "--data", str(store), "--out", str(root / "wm"), "--epochs", "1", "--max-steps", "3",
                 "--batch-size", "8"]) == 0
    return root


def test_eval_conditions_1_and_6_then_resume_and_report(run, capsys):
    args = ["eval", "--conditions", "1,6", "--episodes", "1", "--seed-start", "7", "--out", str(run / "eval"),
            "--wam", str(run / "wam"), "--wm-plain", str(run / "wm"), "--camera-size", "64", "--max-steps", "20",
            "--num-candidates", "4", "--iterations", "1"]  # the default planner (wamplan's MPPI), tiny
    assert main(args) == 0
    recs = {r["condition"]: r for r in read_records(run / "eval")}
    assert set(recs) == {1, 6} and all(r["seed"] == 7 and r["length"] == 20 for r in recs.values())
    assert recs[1]["planned_chunks"] == 0 and recs[6]["planned_chunks"] == 1  # chunk 1 open loop, chunk 2 planned
    (chunk,) = recs[6]["chunks"]
    assert chunk["planned"] and chunk["step"] == 16  # planned where the WAM's second chunk starts
    assert chunk["best_cost"] <= chunk["seed_cost"]  # the WAM's chunk is a candidate: the search never does worse
    assert recs[6]["chunk_timing_s"]["search_s"] == pytest.approx(chunk["search_s"], abs=1e-4)  # the mean of one
    assert [x["t"] for x in recs[1]["trace"]] == [0, 4, 8, 12, 16, 20]  # the cube's privileged path, every 4 steps
    assert recs[1]["trace"][0]["bottom_mm"] == pytest.approx(0, abs=1)
    assert recs[1]["held_at_end"] == recs[1]["trace"][-1]["grasped"] and (recs[1]["release"] is None) == (
        recs[1]["releases"] == 0)
    capsys.readouterr()
    assert main(args) == 0  # resume: nothing left to do
    assert "already recorded" in capsys.readouterr().out and len(read_records(run / "eval")) == 2
    (run / "wam_link").symlink_to(run / "wam")  # the same checkpoint spelled another way is the same setting
    alias = [str(run / "wam_link") if a == str(run / "wam") else a for a in args]
    assert main(alias) == 0 and len(read_records(run / "eval")) == 2
    assert main(["report", str(run / "eval")]) == 0
    assert (run / "eval" / "figure3.png").is_file()
    other = [*args[:-4], "--num-candidates", "8", "--iterations", "1"]
    capsys.readouterr()
    assert main(other) == 2
    said = capsys.readouterr()
    assert "other settings" in said.err and "resuming" not in said.out  # the refusal alone, no resume announced


def test_wm_eval_reports_copy_baseline(run, tmp_path):
    out = tmp_path / "m.json"
    assert main(["wm", "eval", "--ckpt", str(run / "wm"), "--data", str(run / "expert"), "--split", "all",
                 "--horizon", "2", "--json", str(out)]) == 0
    m = json.loads(out.read_text())
    # the copy-the-last-frame baseline, recomputed here from the cached features of the same windows
    from wamplan.data.features import feature_key
    from wamplan.data.readers import WorldModelWindows
    from wamplan.worldmodel.load import load_world_model

    model, enc = load_world_model(run / "wm")
    h = model.cfg.context
    ds = WorldModelWindows([run / "expert"], frameskip=model.cfg.frameskip, history=h, horizon=2, split="all",
                           features=feature_key(enc.config_dict()))
    assert m["windows"] == len(ds) > 0 and m["horizon"] == 2 and m["frameskip"] == model.cfg.frameskip
    held = tmp_path / "wm_held"  # a model trained holding out another share scores that share's episodes
    shutil.copytree(run / "wm" / "checkpoint", held)
    meta = json.loads((held / "config.json").read_text())
    meta["config"]["data"]["val_fraction"] = 0.3
    (held / "config.json").write_text(json.dumps(meta))
    assert main(["wm", "eval", "--ckpt", str(held), "--data", str(run / "expert"), "--horizon", "1",
                 "--json", str(out)]) == 0
    assert json.loads(out.read_text())["val_fraction"] == 0.3
    assert main(["wm", "eval", "--ckpt", str(run / "wm"), "--data", str(run / "expert"), "--horizon", "0"]) == 2
    z = torch.stack([ds[i]["z"].float() for i in range(len(ds))])  # (W, h + 2, V, N, D)
    for k in (1, 2):
        copy = (z[:, h - 1] - z[:, h - 1 + k]).square().flatten(1).mean(1).mean()  # over windows
        assert m[f"copy_z_mse_h{k}"] == pytest.approx(copy.item(), rel=1e-4)
    assert m["copy_z_mse_h2"] > m["copy_z_mse_h1"]  # the scene moves on: two steps away is further
    assert m["z_mse_h1"] != m["copy_z_mse_h1"] and all(map(math.isfinite, (m["z_mse_h1"], m["z_mse_h2"])))


@pytest.mark.slow
def test_eval_kill9_then_resume_loses_and_repeats_nothing(run):
    """kill -9 an evaluation (one process) after its first record; resuming in-process loses and repeats nothing.
    Slow (~40 s: a fresh interpreter, env and WAM); the default suite's kill -9 test is test_data's."""
    import os
    import signal
    import subprocess
    import sys
    import time

    out = run / "eval_kill"
    args = ["eval", "--conditions", "1", "--episodes", "5", "--out", str(out), "--wam", str(run / "wam"),
            "--camera-size", "64", "--max-steps", "40"]
    proc = subprocess.Popen([sys.executable, "-m", "wamplan.cli", *args], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 240
    while time.time() < deadline and len(read_records(out)) < 1:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    before = read_records(out)
    assert 1 <= len(before) < 5, "the kill should land mid-evaluation"
    assert main(args) == 0
    after = read_records(out)
    assert sorted(x["seed"] for x in after) == [0, 1, 2, 3, 4]  # nothing lost, nothing repeated
    assert after[:len(before)] == before  # finished records untouched


def test_explain_draws_one_planned_chunk_in_the_model_and_in_the_simulator(run, capsys):
    assert main(["wm", "train-decoder", "--data", str(run / "expert"), "--out", str(run / "dec"), "--epochs", "1",
                 "--max-steps", "2", "--batch-size", "8"]) == 0
    out = run / "mechanism.png"
    capsys.readouterr()
    assert main(["explain", "--wam", str(run / "wam"), "--wm-augmented", str(run / "wm"), "--decoder",
                 str(run / "dec"), "--seed", "7", "--chunk", "1", "--out", str(out), "--camera-size", "64",
                 "--num-candidates", "4", "--iterations", "1"]) == 0
    m = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out.is_file() and m["step"] == 16
    assert set(m["model_cost"]) == set(m["true_cost"]) == {"wam", "plan"}
    assert all(math.isfinite(v) and v > 0 for d in ("model_cost", "true_cost") for v in m[d].values())
    assert m["model_cost"]["plan"] != m["model_cost"]["wam"]  # the plan moved off the WAM's chunk
    assert main(["explain", "--wam", str(run / "wam"), "--wm-augmented", str(run / "wm"), "--decoder",
                 str(run / "nope"), "--out", str(out)]) == 2
    assert "train-decoder" in capsys.readouterr().err
    for bad, said in [(["--decoder", str(run / "wm")], "holds a 'wm-predictor' checkpoint, not 'wm-decoder'"),
                      (["--decoder", str(run / "dec"), "--chunk", "19"],
                       "chunks the last is chunk 18; pick --chunk 1..18")]:
        assert main(["explain", "--wam", str(run / "wam"), "--wm-augmented", str(run / "wm"), *bad,
                     "--out", str(out)]) == 2  # refused before the episode runs
        assert said in capsys.readouterr().err
    from wamplan.errors import UserError
    from wamplan.worldmodel.decoder import load_decoder

    with pytest.raises(UserError, match="draws views of task 'cube-insertion', the world model is of task 'stack"):
        load_decoder(run / "dec", task="stack-cube")  # the task it was trained on is recorded and checked
