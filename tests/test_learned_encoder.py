"""The ``task-cnn`` encoder: what its state read-out learns from, trained on a store's own frames, frozen, loaded by
the world model that was trained on its features, and refused when its weights are not the ones that model saw."""

import json
import shutil

import h5py
import numpy as np
import pytest
import torch

from wamplan.data.readers import STATE_QUANTITIES, state_targets
from wamplan.errors import UserError

pytestmark = pytest.mark.usefixtures("one_thread")


def test_state_targets_are_the_cube_relative_to_the_tcp_and_in_the_world_in_cm(expert_store):
    path = sorted((expert_store / "episodes").glob("*.h5"))[0]
    with h5py.File(path, "r") as f:
        steps = [0, 4, 8]
        s = state_targets(f, steps)
        cube, tcp = f["cube_pose"][steps][:, :3], f["tcp_pose"][steps][:, :3]
    assert s.shape == (3, len(STATE_QUANTITIES)) and s.dtype == np.float32
    np.testing.assert_allclose(s[:, :3], (cube - tcp) * 100, rtol=1e-6)
    np.testing.assert_allclose(s[:, 3:], cube * 100, rtol=1e-6)


def test_stack_cube_stores_record_both_cubes_and_the_state_is_relative_to_the_target(tmp_path):
    from wamplan.cli import main

    out = tmp_path / "stack"
    assert main(["collect", "--task", "stack-cube", "--source", "pink", "--episodes", "1", "--max-steps", "8",
                 "--camera-size", "64", "--out", str(out)]) == 0
    path = next((out / "episodes").glob("*.h5"))
    with h5py.File(path, "r") as f:
        a, b, tcp = f["cube_pose"][:, :3], f["target_pose"][:, :3], f["tcp_pose"][:, :3]  # (T+1, 3) each
        s = state_targets(f, [0, 8])
    assert a.shape == b.shape == (9, 3) and 0.02 < np.linalg.norm(a[0, :2] - b[0, :2]) < 0.5  # two cubes apart
    np.testing.assert_allclose(s[:, :3], (a - tcp)[[0, 8]] * 100, rtol=1e-6)
    np.testing.assert_allclose(s[:, 3:], (a - b)[[0, 8]] * 100, rtol=1e-6)


@pytest.fixture(scope="module")
def trained(expert_store, tmp_path_factory):
    from wamplan.checkpoint import export_for_inference
    from wamplan.cli import main

    root = tmp_path_factory.mktemp("task_cnn")
    store = root / "expert"
    shutil.copytree(expert_store, store)
    run = root / "enc"
    assert main(["wm", "train-encoder", "--data", str(store), "--out", str(run), "--epochs", "2",
                 "--batch-size", "8", "--width", "32", "--log-every-steps", "1"]) == 0
    export_for_inference(run / "checkpoint", root / "enc16")
    return store, run, root / "enc16"


def test_training_logs_the_state_readout_in_mm_and_the_export_encodes(trained):
    from wamplan.encoders import make_encoder

    store, run, export = trained
    logged = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    val = [m for m in logged if "val/state_mm" in m]
    assert len(val) == 2 and all(m["val/state_mm"] > 0 and m["val/recon_mse"] > 0 for m in val)
    enc = make_encoder("task-cnn", ckpt=str(export))
    images = np.random.default_rng(0).integers(0, 256, (3, 64, 64, 3), dtype=np.uint8)
    z = enc.encode(images)
    assert z.shape == (3, 16, 32) and not any(p.requires_grad for p in enc.parameters())
    cfg = enc.config_dict()
    assert cfg["name"] == "task-cnn" and cfg["ckpt"] == str(export) and len(cfg["sha"]) == 12
    again = make_encoder(**cfg)  # rebuilt from its own record: the same features
    assert torch.equal(again.encode(images), z)
    # the run's float32 weights and the float16 export are different encoders, and a record says which
    with pytest.raises(UserError, match="not the ones this model was trained on"):
        make_encoder("task-cnn", ckpt=str(run / "checkpoint"), sha=cfg["sha"])
    with pytest.raises(UserError, match="needs its trained weights"):
        make_encoder("task-cnn")


def test_a_finished_run_trains_longer_with_its_own_settings(trained, tmp_path, capsys):
    from wamplan.cli import main

    store, run, _ = trained
    longer = tmp_path / "enc"
    shutil.copytree(run, longer)
    # only --epochs given: the run's batch size (8) and width (32) are kept, not the defaults (64, 128)
    assert main(["wm", "train-encoder", "--data", str(store), "--out", str(longer), "--epochs", "3"]) == 0, \
        capsys.readouterr().err
    logged = [json.loads(line) for line in (longer / "metrics.jsonl").read_text().splitlines()]
    assert len([m for m in logged if "val/state_mm" in m]) == 3


def test_a_world_model_trains_on_its_features_and_reloads_it_from_any_folder(trained, tmp_path, monkeypatch):
    from wamplan.cli import main
    from wamplan.worldmodel.load import load_world_model

    store, _, export = trained
    repo = tmp_path / "repo"  # the encoder named relative to the folder the model is trained in
    shutil.copytree(export, repo / "checkpoints" / "enc16")
    monkeypatch.chdir(repo)
    assert main(["wm", "train", "--data", str(store), "--out", "runs/wm", "--max-steps", "1", "--batch-size", "4",
                 "--encoder", "task-cnn", "--encoder-kwargs", json.dumps({"ckpt": "checkpoints/enc16"})]) == 0
    monkeypatch.chdir(tmp_path)  # elsewhere: found above the world model, recorded as it was given
    model, enc = load_world_model(repo / "runs" / "wm")
    assert enc.name == "task-cnn" and (model.cfg.encoder, model.cfg.num_patches, model.cfg.enc_dim) == ("task-cnn", 16, 32)
    assert enc.config_dict()["ckpt"] == "checkpoints/enc16"
    assert enc.config_dict()["sha"] == load_world_model(repo / "runs" / "wm")[1].config_dict()["sha"]
    shutil.move(repo / "runs", tmp_path / "moved")  # out of the tree that holds its encoder: said in one line
    with pytest.raises(UserError, match="reads its task-cnn encoder's weights from checkpoints/enc16"):
        load_world_model(tmp_path / "moved" / "wm")
