"""Every failure a user can cause ends in one line that names the flag or file they gave and the fix, exit status
2 and no traceback (issue 39's battery): damaged checkpoints, bad seeds, devices and backends, output paths that
are files, damaged episode files, a failed evaluation start, bad /act requests, and argparse's own errors.

Each case runs ``wamplan`` in-process and stops before any episode runs, so the battery takes seconds."""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import requests

from wamplan.cli import main

MINI = Path(__file__).resolve().parents[1] / "checkpoints" / "mini"


def refused(capsys, argv: list, *named: object) -> str:
    """Run ``wamplan argv``: exit status 2, no traceback, one error line naming each of ``named`` -> that line."""
    try:
        code = main([str(a) for a in argv])
    except SystemExit as e:  # argparse's own errors
        code = e.code
    out, err = capsys.readouterr()
    refused.out = out  # what it printed before the error (e.g. data check's list of damaged files)
    assert code == 2, err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if re.match(r"wamplan( [\w-]+)*: error: ", line)]
    assert len(lines) == 1, err
    for n in named:
        assert str(n) in lines[0], (n, lines[0])
    return lines[0]


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory) -> Path:
    """Copies of the shipped mini checkpoints (the cases below damage copies of these copies)."""
    root = tmp_path_factory.mktemp("ckpts")
    for name in ("tinywam", "wm_augmented"):
        shutil.copytree(MINI / name, root / name)
    return root


def _copy(ckpts: Path, name: str, tmp_path: Path) -> Path:
    return Path(shutil.copytree(ckpts / name, tmp_path / f"bad_{name}"))


def _truncate(path: Path, keep: int) -> None:
    path.write_bytes(path.read_bytes()[:keep])


# ------------------------------------------------------------------------------------------------ checkpoints
def test_truncated_or_empty_weights(ckpts, tmp_path, capsys):
    wam = _copy(ckpts, "tinywam", tmp_path)
    weights = wam / "model.safetensors"
    _truncate(weights, 1000)
    out = tmp_path / "eval"
    line = refused(capsys, ["eval", "--conditions", "1", "--episodes", "1", "--out", out, "--wam", wam], weights)
    assert "damaged or incomplete" in line and "restore it" in line
    assert not (out / "eval_config.json").exists()  # a failed start stores no settings
    refused(capsys, ["env", "rollout", "--policy", wam, "--episodes", "1"], weights)
    weights.write_bytes(b"")
    refused(capsys, ["wam", "serve", "--ckpt", wam], weights)


def test_nan_weights_are_damage_found_on_load(ckpts, tmp_path):
    from safetensors.torch import load_file, save_file

    wam = _copy(ckpts, "tinywam", tmp_path)
    weights = load_file(str(wam / "model.safetensors"))
    name = next(k for k, t in weights.items() if t.is_floating_point())
    weights[name][...] = float("nan")
    save_file(weights, str(wam / "model.safetensors"))
    from wamplan.checkpoint import CheckpointError
    from wamplan.wam import load_wam

    with pytest.raises(CheckpointError, match=rf"model.safetensors is damaged: tensor\(s\) \['{re.escape(name)}'\] "
                                              r"hold NaN"):
        load_wam(wam, device="cpu")  # on load, before any query


@pytest.mark.parametrize("damage", [b"{not json", b"\xff\xfe\x00garbage"])
def test_garbage_or_non_utf8_config(ckpts, tmp_path, capsys, damage):
    wm = _copy(ckpts, "wm_augmented", tmp_path)
    (wm / "config.json").write_bytes(damage)
    line = refused(capsys, ["eval", "--conditions", "7", "--episodes", "1", "--out", tmp_path / "eval",
                            "--wam", ckpts / "tinywam", "--wm-augmented", wm], wm / "config.json")
    assert "not a JSON file" in line
    wam = _copy(ckpts, "tinywam", tmp_path)
    (wam / "config.json").write_bytes(damage)
    refused(capsys, ["wam", "serve", "--ckpt", wam], wam / "config.json")


def test_a_config_without_a_kind_is_not_a_checkpoint_config(ckpts, tmp_path, capsys):
    wam = _copy(ckpts, "tinywam", tmp_path)
    (wam / "config.json").write_text("{}")
    line = refused(capsys, ["wam", "serve", "--ckpt", wam], wam / "config.json", "is not a wamplan checkpoint config")
    assert "None" not in line


def test_config_that_no_longer_fits_the_weights(ckpts, tmp_path, capsys):
    wm = _copy(ckpts, "wm_augmented", tmp_path)
    meta = json.loads((wm / "config.json").read_text())
    meta["config"]["predictor"]["mlp_dim"] = 256  # the weights were trained with 384
    (wm / "config.json").write_text(json.dumps(meta))
    line = refused(capsys, ["eval", "--conditions", "7", "--episodes", "1", "--out", tmp_path / "eval",
                            "--wam", ckpts / "tinywam", "--wm-augmented", wm], wm)
    assert "this checkpoint's weights do not match its config.json: size mismatch" in line


def test_a_world_model_where_a_wam_belongs(ckpts, tmp_path, capsys):
    wm = ckpts / "wm_augmented"
    for argv in (["eval", "--conditions", "1", "--episodes", "1", "--out", tmp_path / "eval", "--wam", wm],
                 ["collect", "--source", "policy", "--policy", wm, "--episodes", "1", "--out", tmp_path / "store",
                  "--camera-size", "64"]):
        line = refused(capsys, argv, wm, "not a WAM")
        assert "--ckpt" not in line  # a flag the user did not type


# ------------------------------------------------------------------------------- seeds, devices, backends, paths
@pytest.mark.parametrize("argv, flag", [
    (["eval", "--seed-start", "-1", "--episodes", "1", "--wam", "x"], "--seed-start -1"),
    (["eval", "--seed-start", str(2**32 - 1), "--episodes", "2", "--wam", "x"], "--seed-start 4294967295"),
    (["collect", "--source", "expert", "--seed-start", "-1", "--episodes", "1"], "--seed-start -1"),
    (["env", "render", "--seed", "-3"], "--seed -3"),
])
def test_seeds_outside_32_bits(tmp_path, capsys, argv, flag):
    out = tmp_path / "out"
    refused(capsys, [*argv, "--out", out], flag, "0 .. 4294967295")
    assert not out.exists()


def test_number_lists_parse_ranges_and_refuse_garbage_in_one_line():
    from wamplan.config import int_list
    from wamplan.errors import UserError

    assert int_list("500-502, 510,7", "--seeds") == [500, 501, 502, 510, 7]
    with pytest.raises(UserError, match="--seeds '2-x' is not a list like 500-503 or 500,510"):
        int_list("2-x", "--seeds")
    with pytest.raises(UserError, match="--seeds needs at least one number"):
        int_list(" , ", "--seeds")
    with pytest.raises(UserError, match="--steps '160-128': the range 160-128 runs backwards; write 128-160"):
        int_list("160-128", "--steps")
    from wamplan.evaluation.conditions import parse_conditions

    with pytest.raises(UserError, match="--conditions '7-1': the range 7-1 runs backwards; write 1-7"):
        parse_conditions("7-1")
    with pytest.raises(UserError, match="--conditions needs at least one number, e.g. 1,6,7"):
        parse_conditions("")


def test_a_json_file_under_a_file_is_refused_before_any_work_and_a_missing_folder_is_made(tmp_path, capsys):
    from wamplan.cli.wm import write_json

    base = ["wm", "fidelity", "--wam", "checkpoints/mini/tinywam", "--wm", "checkpoints/mini/wm_augmented",
            "--seeds", "500"]
    (tmp_path / "f").write_text("")
    refused(capsys, [*base, "--json", tmp_path / "f" / "x.json"], "--json", "is a file, not a folder")
    refused(capsys, [*base, "--boundaries", "x"], "--boundaries 'x' is not a list like 2-8 or 2,5,8")
    assert json.loads(write_json(tmp_path / "new" / "x.json", {"a": 1}).read_text()) == {"a": 1}

def test_a_nan_gate_is_refused():
    from wamplan.config import ConfigError
    from wamplan.planning.policy_config import PlannedPolicyConfig

    with pytest.raises(ConfigError, match="gate_threshold must be a finite number, got nan"):
        PlannedPolicyConfig(gate_threshold=float("nan"))


@pytest.mark.skipif(__import__("torch").cuda.is_available(), reason="this machine has CUDA")
def test_cuda_where_torch_has_none(ckpts, tmp_path, capsys):
    for argv in (["eval", "--conditions", "1", "--episodes", "1", "--out", tmp_path / "e", "--wam",
                  ckpts / "tinywam", "--device", "cuda"],
                 ["wam", "serve", "--ckpt", ckpts / "tinywam", "--device", "cuda"],
                 ["wm", "probe", "--data", tmp_path, "--device", "cuda"]):
        refused(capsys, argv, "--device cuda", "--device cpu")
    refused(capsys, ["wam", "serve", "--ckpt", ckpts / "tinywam", "--device", "cuda:x"], "is not a torch device")


@pytest.mark.parametrize("argv", [
    ["eval", "--conditions", "1", "--episodes", "1", "--wam", "x"],
    ["collect", "--source", "expert", "--episodes", "1"],
    ["env", "render"],
])
def test_bogus_render_backend_before_any_work(tmp_path, capsys, argv):
    out = tmp_path / ("v.png" if argv[0] == "env" else "out")
    refused(capsys, [*argv, "--out", out, "--render-backend", "bogus"], "--render-backend 'bogus'", "cpu, gpu")
    assert not out.exists()


def test_out_that_is_a_file(tmp_path, capsys):
    f = tmp_path / "a_file"
    f.write_text("x")
    refused(capsys, ["collect", "--source", "expert", "--episodes", "1", "--out", f], f"--out {f} is a file")
    refused(capsys, ["eval", "--conditions", "1", "--episodes", "1", "--out", f, "--wam", MINI / "tinywam"],
            f"--out {f} is a file")
    refused(capsys, ["data", "info", f], f, "is a file")


def _unwritable(tmp_path: Path) -> Path:
    """A directory in which no file can be created: a 0o555 one (root ignores its mode: then /sys, which refuses
    new files to root too); skips where neither holds."""
    ro = tmp_path / "read_only"
    ro.mkdir()
    ro.chmod(0o555)
    for d in (ro, Path("/sys")):
        try:
            (d / "probe").mkdir()
        except OSError:
            return d
        (d / "probe").rmdir()
    pytest.skip("no unwritable directory here")


@pytest.mark.parametrize("argv", [
    ["eval", "--conditions", "1", "--episodes", "1", "--wam", MINI / "tinywam"],
    ["collect", "--source", "expert", "--episodes", "1"],
    ["wm", "train", "--data", "nosuch"],
    ["wam", "train", "--data", "nosuch"],
])
def test_out_that_cannot_be_written_before_any_work(tmp_path, capsys, argv):
    ro = _unwritable(tmp_path)
    refused(capsys, [*argv, "--out", ro / "out"], f"--out {ro / 'out'} cannot be written", "you can write")
    in_the_way = tmp_path / "a_file"
    in_the_way.write_text("x")
    refused(capsys, [*argv, "--out", in_the_way / "out"], f"{in_the_way} is a file")


def test_encoding_a_store_that_cannot_be_written(expert_store, tmp_path, capsys):
    """wm encode writes its cache into the store: a store it cannot write is refused before any encoding; one whose
    features are all cached is only read."""
    store = Path(shutil.copytree(expert_store, tmp_path / "store"))
    shutil.rmtree(store / "features", ignore_errors=True)
    (store / "features").write_text("in the way")  # where the cache's directory must go
    refused(capsys, ["wm", "encode", "--data", store], f"{store / 'features'} is a file")
    (store / "features").unlink()
    assert main(["wm", "encode", "--data", str(store)]) == 0
    capsys.readouterr()
    store.chmod(0o555)
    try:
        assert main(["wm", "encode", "--data", str(store)]) == 0  # all cached: nothing to write
    finally:
        store.chmod(0o755)


# ------------------------------------------------------------------------------------------- damaged episodes
def _damage_image_chunk(path: Path) -> None:
    """Overwrite 8 bytes in the middle of one stored image (a chunk of the data, not the file's structure)."""
    with h5py.File(path, "r") as f:
        info = f["images/front"].id.get_chunk_info(0)  # the first frame, which every reader reads
    data = bytearray(path.read_bytes())
    mid = info.byte_offset + info.size // 2
    data[mid:mid + 8] = bytes(255 - b for b in data[mid:mid + 8])
    path.write_bytes(bytes(data))


def test_damaged_episode_is_named_by_check_view_and_encode(expert_store, tmp_path, capsys):
    store = Path(shutil.copytree(expert_store, tmp_path / "store"))
    bad = sorted((store / "episodes").glob("*.h5"))[1]
    _damage_image_chunk(bad)
    assert main(["data", "info", str(store)]) == 0  # headers intact: counted, and it says how to read every byte
    assert "wamplan data check" in capsys.readouterr().out
    refused(capsys, ["data", "check", store], "1 of 2 episode files", "re-run the same `wamplan collect`")
    assert f"damaged: {bad} (OSError" in refused.out  # listed above the error line, with HDF5's reason
    refused(capsys, ["data", "view", store, "--episode", "1", "--out", tmp_path / "s.png"], bad, "damaged")
    refused(capsys, ["wm", "encode", "--data", store], bad, "damaged")


def test_a_truncated_episode_is_not_counted_as_collected(expert_store, tmp_path, capsys):
    store = Path(shutil.copytree(expert_store, tmp_path / "store"))
    bad = sorted((store / "episodes").glob("*.h5"))[1]
    _truncate(bad, bad.stat().st_size // 2)  # cut mid-file, as a full disk or a bad copy leaves it
    refused(capsys, ["collect", "--source", "expert", "--episodes", "2", "--out", store, "--camera-size", "64"],
            bad, "damaged", "re-run the same `wamplan collect`")
    refused(capsys, ["data", "alignment", store], bad, "damaged")


def test_an_episode_damaged_inside_its_images_is_not_counted_as_collected(expert_store, tmp_path, capsys):
    """Damage inside an image chunk leaves the header readable; resuming reads every byte and names the file."""
    store = Path(shutil.copytree(expert_store, tmp_path / "store"))
    bad = sorted((store / "episodes").glob("*.h5"))[1]
    with h5py.File(bad, "r") as f:
        ds = f["images/wrist"]
        info = ds.id.get_chunk_info(ds.id.get_num_chunks() - 1)  # the last frame's chunk, which no header read touches
    data = bytearray(bad.read_bytes())
    mid = info.byte_offset + info.size // 2
    data[mid:mid + 8] = bytes(255 - b for b in data[mid:mid + 8])
    bad.write_bytes(bytes(data))
    assert main(["data", "info", str(store)]) == 0  # the header still reads
    capsys.readouterr()
    refused(capsys, ["collect", "--source", "expert", "--episodes", "2", "--out", store, "--camera-size", "64"],
            bad, "damaged", "re-run the same `wamplan collect`")


def test_data_check_lists_each_damaged_file(expert_store, tmp_path, capsys):
    store = Path(shutil.copytree(expert_store, tmp_path / "store"))
    first, second = sorted((store / "episodes").glob("*.h5"))
    _damage_image_chunk(first)
    second.write_bytes(b"\x00" * 512 + second.read_bytes()[512:])  # its header: even opening it fails
    refused(capsys, ["data", "check", store], "2 of 2 episode files")
    assert f"damaged: {first}" in refused.out and f"damaged: {second}" in refused.out
    refused(capsys, ["data", "info", store], "1 of 2 episode files", second.name)  # info counts the readable one
    assert f"damaged: episode file {second}" in refused.out


def test_every_dataset_of_a_written_episode_is_checksummed(tmp_path):
    """A new episode file carries fletcher32 on every dataset: damage inside any dataset's data, the uncompressed
    arrays included (which nothing else would notice), fails the read instead of returning other numbers."""
    from wamplan.data.store import EpisodeData, EpisodeStore, StoreError, verify_episode
    from wamplan.envs.config import EnvConfig

    env = EnvConfig(camera_size=16)
    task = env.spec
    store = EpisodeStore(tmp_path / "store", create=True, env=env.task_kwargs(), image_every=4)
    rng = np.random.default_rng(0)
    T, arr = 8, lambda *shape: rng.normal(size=shape).astype(np.float32)  # noqa: E731
    ep = EpisodeData(seed=1, source="expert", success=False, outcome="never_grasped", actions=arr(T, task.action_dim),
                     proprio=arr(T + 1, task.proprio_dim), stages=rng.random((T + 1, len(task.stages))) < 0.5,
                     cube_pose=arr(T + 1, 7), tcp_pose=arr(T + 1, 7), sim_state=arr(T + 1, 40),
                     drive_targets=arr(T + 1, 9), image_steps=np.array([0, 4, 8]),
                     images={c: rng.integers(0, 256, (3, 16, 16, 3), np.uint8) for c in task.cameras},
                     reached={s: False for s in task.stages}, policy={}, provenance={})
    path = store.write(ep)
    assert verify_episode(path) == (None, True)  # (no problem, every dataset checksummed)
    with h5py.File(path, "r") as f:
        names: list[str] = []
        f.visititems(lambda name, obj: names.append(name) if isinstance(obj, h5py.Dataset) else None)
        spans = {}
        for name in names:
            ds = f[name]
            info = ds.id.get_chunk_info(0) if ds.chunks else None  # contiguous data: one span
            spans[name] = (info.byte_offset, info.size) if info else (ds.id.get_offset(), ds.id.get_storage_size())
    assert len(names) == 11  # 8 arrays and the 3 cameras
    intact = path.read_bytes()
    for name, (offset, size) in spans.items():
        data = bytearray(intact)
        at = offset + size // 2
        data[at:at + 4] = bytes(255 - b for b in data[at:at + 4])
        path.write_bytes(bytes(data))
        with pytest.raises(StoreError, match="damaged"):
            store.load(path)
        assert verify_episode(path)[0] is not None, name
    path.write_bytes(intact)
    np.testing.assert_array_equal(store.load(path).actions, ep.actions)


def test_an_old_store_without_checksums_still_reads(expert_store, tmp_path, capsys):
    """Stores written before checksums (h5py's default format, no fletcher32) read as before."""
    from wamplan.data.readers import WAMSamples
    from wamplan.data.store import EpisodeStore

    store = Path(shutil.copytree(expert_store, tmp_path / "store"))
    for path in (store / "episodes").glob("*.h5"):
        old = path.with_suffix(".old")
        with h5py.File(path, "r") as src, h5py.File(old, "w") as dst:
            dst.attrs.update(dict(src.attrs))
            names: list[str] = []
            src.visititems(lambda name, obj: names.append(name) if isinstance(obj, h5py.Dataset) else None)
            for name in names:
                dst.create_dataset(name, data=src[name][()], chunks=src[name].chunks,
                                   compression=src[name].compression)
        old.replace(path)
        with h5py.File(path, "r") as f:
            assert not f["actions"].fletcher32
    assert main(["data", "check", str(store)]) == 0
    assert "2 written before checksums" in capsys.readouterr().out
    s = EpisodeStore(store)
    assert len(s.load(s.episode_paths()[0]).actions) > 0 and len(WAMSamples([store], split="all")[0]) > 0


def test_training_on_a_source_the_store_does_not_hold(expert_store, tmp_path, capsys):
    line = refused(capsys, ["wam", "train", "--data", expert_store, "--sources", "expert,nosuch", "--out",
                            tmp_path / "wam"], "no episodes of source 'nosuch'", "their sources are expert")
    assert "0 items" not in line


def test_eval_refuses_to_write_into_a_store_or_a_training_run(expert_store, tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "metrics.jsonl").write_text("{}\n")
    for out in (expert_store, run):
        before = sorted(p.name for p in out.iterdir())
        refused(capsys, ["eval", "--conditions", "1", "--episodes", "1", "--out", out, "--wam", MINI / "tinywam"],
                f"--out {out} exists and is not an evaluation directory", "pass a new or empty directory")
        assert sorted(p.name for p in out.iterdir()) == before


def test_collect_refuses_a_store_of_another_source(expert_store, tmp_path, capsys):
    """The store's files under the expert's names hold another source's episodes: collect must not mix them."""
    store = Path(shutil.copytree(expert_store, tmp_path / "store"))
    for path in (store / "episodes").glob("*.h5"):
        with h5py.File(path, "r+") as f:
            f.attrs["source"] = "policy:expert"
    before = sorted(p.name for p in (store / "episodes").iterdir())
    refused(capsys, ["collect", "--source", "expert", "--episodes", "3", "--out", store, "--camera-size", "64"],
            store, "holds episodes of source 'policy:expert'")
    assert sorted(p.name for p in (store / "episodes").iterdir()) == before


def test_importing_a_file_that_is_not_hdf5_leaves_nothing_beside_it(tmp_path, capsys):
    traj = tmp_path / "demos" / "trajectory.h5"
    traj.parent.mkdir()
    traj.write_text("not an HDF5 file")
    traj.with_suffix(".json").write_text(json.dumps({"env_info": {"env_id": "PegInsertionSide-v1", "env_kwargs": {
        "control_mode": "pd_joint_pos"}}, "episodes": [{"episode_id": 0}]}))
    line = refused(capsys, ["data", "import", traj, tmp_path / "store", "--format", "maniskill"], traj,
                   "is not an HDF5 file")
    assert "pd_joint_pos" not in line
    assert sorted(p.name for p in traj.parent.iterdir()) == ["trajectory.h5", "trajectory.json"]
    h5py.File(traj, "w").close()  # an HDF5 file, but its .json is not ManiSkill's
    traj.with_suffix(".json").write_text("[]")
    refused(capsys, ["data", "import", traj, tmp_path / "store", "--format", "maniskill"], traj.with_suffix(".json"),
            "is not a ManiSkill trajectory's metadata")


# ---------------------------------------------------------------------------------------- a failed start
def test_a_failed_eval_start_does_not_lock_its_folder(ckpts, tmp_path, capsys):
    wam = _copy(ckpts, "tinywam", tmp_path)
    weights = (wam / "model.safetensors").read_bytes()
    _truncate(wam / "model.safetensors", 100)
    out = tmp_path / "eval"
    argv = ["eval", "--conditions", "1", "--episodes", "1", "--out", out, "--wam", wam, "--camera-size", "64",
            "--max-steps", "2"]
    refused(capsys, argv, wam)
    assert not out.exists()  # not even an empty folder is left behind
    (wam / "model.safetensors").write_bytes(weights)  # the mistake fixed, the same command again
    assert main([str(a) for a in argv]) == 0
    assert json.loads((out / "eval_config.json").read_text())["wam"] == str(wam)


@pytest.mark.parametrize("extra, named", [
    (["--render-backend", "none"], "--render-backend none renders no camera views"),
    (["--cost-view-weights", "1", "1"], "--cost-view-weights gives 2 weights, but task 'cube-insertion' has 3"),
    (["--num-optimized", "20"], "num_optimized=20 exceeds task 'cube-insertion''s 16-step chunk"),
    (["--init-std-per-dim", "0.1", "0.1"], "init_std_per_dim has 2 entries but task 'cube-insertion' has 5-D"),
])
def test_eval_settings_the_run_cannot_use_are_refused_before_any_work(ckpts, tmp_path, capsys, extra, named):
    out = tmp_path / "eval"
    refused(capsys, ["eval", "--conditions", "1,7", "--episodes", "1", "--out", out, "--wam", ckpts / "tinywam",
                     "--wm-augmented", ckpts / "wm_augmented", *extra], named)
    assert not out.exists()


def test_commands_that_need_views_refuse_no_renderer_before_any_work(tmp_path, capsys):
    out = tmp_path / "store"
    for argv in (["collect", "--source", "expert", "--episodes", "1", "--out", out],
                 ["env", "render", "--out", tmp_path / "v.png"],
                 ["env", "rollout", "--policy", MINI / "tinywam", "--episodes", "1"]):
        refused(capsys, [*argv, "--render-backend", "none"], "--render-backend none renders no camera views",
                "pass --render-backend cpu")
    assert not out.exists() and not (tmp_path / "v.png").exists()


def test_settings_stored_without_records_do_not_lock_the_folder(tmp_path):
    """A run that stopped before its first record stored its settings; the corrected command replaces them."""
    from wamplan.errors import UserError
    from wamplan.evaluation.config import EvalConfig
    from wamplan.evaluation.records import append_record
    from wamplan.evaluation.runner import run_evaluation
    from wamplan.planning.policy_config import PlannedPolicyConfig

    out = tmp_path / "eval"
    out.mkdir()
    (out / "eval_config.json").write_text(json.dumps({"planner": "wamplan", "policy.warm_weight": 0.3}))
    cfg = EvalConfig(wam=str(MINI / "tinywam"), policy=PlannedPolicyConfig(warm_weight=0.8))
    run_evaluation(cfg, [1], [], out)  # no jobs: only the settings
    assert json.loads((out / "eval_config.json").read_text())["policy.warm_weight"] == 0.8
    append_record(out, dict(condition=1, seed=0, variant="open-loop"))
    with pytest.raises(UserError, match="holds an evaluation with other settings"):
        run_evaluation(dataclasses.replace(cfg, policy=PlannedPolicyConfig(warm_weight=0.2)), [1], [], out)


# --------------------------------------------------------------------------------------------- /act requests
@pytest.fixture(scope="module")
def act_server():
    from wamplan.envs.contract import CAMERAS
    from wamplan.wam.base import WAM, WAMError, WAMOutput
    from wamplan.serving.runner import BackgroundServer
    from wamplan.wam.server import create_app

    class StrictWAM(WAM):
        """Refuses an instruction it was not trained on: a well-formed request the server answers with 422 (a
        proprio of another length is fitted by the server, so it reaches the WAM 10-D)."""

        name = "strict"

        def predict(self, obs, instruction):
            assert obs.proprio.shape == (10,)
            if instruction != "t":
                raise WAMError(f"knows only the instruction 't', got {instruction!r}")
            return WAMOutput(actions=np.zeros((16, 5), np.float32), images={c: obs.images[c] for c in CAMERAS})

    with BackgroundServer(create_app(StrictWAM())) as srv:
        yield srv


def _body(**changes) -> str:
    import json_numpy

    img = np.zeros((8, 8, 3), np.uint8)
    payload = dict(primary_image=img, left_wrist_image=img, right_wrist_image=img,
                   proprio=np.zeros(10, np.float32), task_description="t")
    payload.update(changes)
    return json_numpy.dumps(payload)


@pytest.mark.parametrize("body, status, reason", [
    ("{not json", 400, "not valid json_numpy JSON"),
    (_body(primary_image=np.zeros((8, 8), np.uint8)), 400, "has shape (8, 8), expected (h, w, 3)"),
    (_body(primary_image=np.zeros((8, 8, 3), np.float32)), 400, "has dtype float32, expected uint8"),
    (_body(proprio=np.array([np.nan] * 10, np.float32)), 400, "non-finite values"),
    (_body(task_description="fold the shirt"), 422, "knows only the instruction 't'"),
    (_body(left_wrist_image=np.zeros((8, 16, 3), np.uint8)), 400,
     "'left_wrist_image' has shape (8, 16, 3) but 'primary_image' has (8, 8, 3)"),
    ("[" * 100_000 + "]" * 100_000, 400, "nests JSON arrays or objects too deeply"),
])
def test_bad_act_requests_get_a_4xx_and_the_reason(act_server, body, status, reason):
    r = requests.post(f"{act_server.url}/act", data=body, headers={"Content-Type": "application/json"}, timeout=10)
    assert r.status_code == status and reason in r.json()["error"]


def test_the_client_prints_the_servers_reason(act_server):
    from wamplan.envs.contract import CAMERAS, Observation
    from wamplan.errors import UserError
    from wamplan.wam.base import WAMServerError
    from wamplan.wam.cosmos_client import CosmosPolicyClient

    client = CosmosPolicyClient(url=f"{act_server.url}/act")
    obs = Observation(step=0, proprio=np.zeros(10, np.float32), images={c: np.zeros((8, 8, 3), np.uint8)
                                                                        for c in CAMERAS})
    assert client.predict(obs, "t").actions.shape == (16, 5)
    with pytest.raises(WAMServerError, match=r"refused the request \(HTTP 422: the WAM 'strict' cannot answer this "
                                             r"request: knows only the instruction 't', got 'fold'\)"):
        client.predict(obs, "fold")
    floats = Observation(step=0, proprio=np.zeros(10, np.float32), images={c: np.full((8, 8, 3), 0.5, np.float32)
                                                                           for c in CAMERAS})
    with pytest.raises(UserError, match="the Cosmos client: the '.*' image is float32"):  # not cast to black bytes
        client.predict(floats, "t")


def test_a_directory_of_another_kind_is_named_with_what_it_holds(tmp_path, capsys):
    wam = MINI / "tinywam"
    refused(capsys, ["report", wam], "is not an evaluation directory (it holds a 'tinywam' checkpoint)",
            "made by `wamplan eval`")  # not "run `wamplan eval --out CHECKPOINT`", which eval refuses
    refused(capsys, ["data", "info", wam], "is not a wamplan episode store (it holds a 'tinywam' checkpoint)",
            "`wamplan collect` or `wamplan data import`")
    refused(capsys, ["gate-calibrate", tmp_path / "none"], "does not exist; pass an evaluation directory")
    started = tmp_path / "started"  # an evaluation whose first episode has not finished: not "another kind"
    started.mkdir()
    (started / "eval_config.json").write_text("{}")
    for argv in (["report", started], ["gate-calibrate", started]):
        refused(capsys, argv, "holds an evaluation whose first episode has not finished; run or resume `wamplan "
                              f"eval --out {started}`")
    refused(capsys, ["gate-calibrate", tmp_path, "--quantiles", "0.5", "1.5"], "--quantiles 1.5", "[0, 1]")
    refused(capsys, ["env", "check", "--steps", "0"], "--steps must be >= 1")
    refused(capsys, ["data", "import", "--format", "maniskill", tmp_path / "no.h5", tmp_path / "o"],
            "no.h5 does not exist; pass a ManiSkill trajectory file")
    refused(capsys, ["collect", "--source", "expert", "--task", "push-cube", "--episodes", "1", "--out",
                     tmp_path / "o"], "no scripted expert", "--source pink", "`wamplan data import`")
    assert not (tmp_path / "o").exists()


def test_a_bad_value_is_named_by_its_option(tmp_path, capsys):
    # config errors name fields (TrainConfig.epochs, warmup_epochs, frameskip); the command line names its options
    wm = ["wm", "train", "--data", tmp_path, "--out", tmp_path / "run"]
    assert refused(capsys, [*wm, "--epochs", "0"], "error: --epochs must be a positive int").count("Config") == 0
    refused(capsys, [*wm, "--warmup-epochs", "99"], "error: --warmup-epochs must be in [0, --epochs=")
    refused(capsys, [*wm, "--frameskip", "0"], "error: --frameskip must be a positive int")
    refused(capsys, ["eval", "--conditions", "7", "--out", tmp_path / "e", "--wam", MINI / "tinywam", "--wm-augmented",
                     MINI / "wm_augmented", "--cost-pool", "3"], "--cost-pool 3", "pass a divisor of 4")
    assert not (tmp_path / "e").exists()


def test_numbers_that_are_not_finite_are_named_by_their_option_before_any_work(tmp_path, capsys):
    wm = ["wm", "train", "--data", tmp_path, "--out", tmp_path / "run"]
    refused(capsys, [*wm, "--change-weight", "inf"], "error: --change-weight must be a finite number, got inf")
    refused(capsys, [*wm, "--lr", "nan"], "error: --lr must be a finite number, got nan")
    refused(capsys, ["eval", "--conditions", "7", "--out", tmp_path / "e", "--wam", MINI / "tinywam", "--wm-augmented",
                     MINI / "wm_augmented", "--warm-weight", "inf"], "--warm-weight must be a finite")
    refused(capsys, ["eval", "--conditions", "7", "--out", tmp_path / "e", "--wam", MINI / "tinywam", "--wm-augmented",
                     MINI / "wm_augmented", "--temperature=-inf"], "--temperature must be a finite number")
    refused(capsys, ["collect", "--source", "expert", "--episodes", "1", "--max-steps", "-4", "--out", tmp_path / "c"],
            "--max-steps -4 must be at least 1")
    assert not any(p.exists() for p in (tmp_path / "run", tmp_path / "e", tmp_path / "c"))
    from wamplan.config import ConfigError
    from wamplan.planning.policy import PlannedPolicyConfig

    with pytest.raises(ConfigError, match="warm_weight must be a finite number, got '1'"):
        PlannedPolicyConfig(warm_weight="1")  # a string from a hand-written call: named, not a TypeError
    import numpy as np
    import torch

    from wamplan.planning.cost_config import CostConfig
    from wamplan.worldmodel.config import TrainConfig

    assert CostConfig(view_weights=[0, 0, 1]).view_weights == [0, 0, 1]  # lists, arrays and 0-d tensors are numbers
    assert float(TrainConfig(lr=torch.tensor(1e-3)).lr) == pytest.approx(1e-3) and TrainConfig(lr=np.float32(1)).lr
    with pytest.raises(ConfigError, match=r"view_weights must be finite numbers, got nan in \(0, nan, 1\)"):
        CostConfig(view_weights=(0, float("nan"), 1))
    refused(capsys, ["wm", "fidelity", "--wam", "w", "--wm", "x=y", "--seeds", "1", "--sigma", "nan"],
            "--sigma must be a finite number, got nan")


def test_step_limits_below_one_are_refused(tmp_path):
    from wamplan.envs.config import EnvConfig
    from wamplan.envs.core import TaskEnv
    from wamplan.policies.rollout import run_episode
    import torch

    from wamplan.errors import UserError
    from wamplan.train_loop import AdamWConfig, fit

    with pytest.raises(UserError, match="--max-steps 0 must be at least 1"):
        fit(torch.nn.Linear(1, 1), [0] * 4, lambda m, b: (m.weight.sum(), {}), AdamWConfig(batch_size=1),
            run_dir=tmp_path / "run", kind="k", config={}, max_steps=0)
    assert not (tmp_path / "run").exists()
    env = TaskEnv(EnvConfig())
    try:
        with pytest.raises(ValueError, match="max_steps must be >= 1"):
            run_episode(env, None, seed=0, max_steps=0)
    finally:
        env.close()


def test_report_refuses_a_directory_named_twice(tmp_path, capsys):
    from wamplan.evaluation.records import append_record

    run = tmp_path / "run"
    run.mkdir()
    append_record(run, dict(condition=1, seed=0, variant="open-loop", success=False, outcome="failure", length=10))
    refused(capsys, ["report", run, f"{run}/"], "is named twice; name each evaluation directory once")


def test_a_mistyped_option_gets_the_nearest_one(tmp_path, capsys):
    refused(capsys, ["eval", "--out", tmp_path, "--wm-augmneted", "x"],
            "unrecognized arguments: --wm-augmneted x; did you mean --wm-augmented?")
    assert "did you mean" not in refused(capsys, ["eval", "--out", tmp_path, "--zzzz"], "--zzzz")
    # only options the command takes, never the refused one itself, never a flag its help merely mentions
    assert "did you mean" not in refused(capsys, ["data", "info", tmp_path, "--out", "x"], "--out x")
    serve = ["serve", "--upstream", "w", "--world-model", "x"]  # its help mentions `wm train --data`
    assert "did you mean" not in refused(capsys, [*serve, "--datta", "1"], "--datta")  # --data
    fidelity = ["wm", "fidelity", "--wam", "w", "--wm", "x=y", "--seeds", "1"]
    assert refused(capsys, [*fidelity, "--plan-view-weigths", "1"], "--plan-view-weigths").endswith(
        "did you mean --plan-view-weights?")  # an option it has, not one its help text names


def test_reproduce_checks_its_inputs_before_hours_of_work(tmp_path, capsys, monkeypatch):
    out = tmp_path / "r"
    refused(capsys, ["reproduce", "--out", out, "--wam", tmp_path / "none"], "is not a wamplan checkpoint")
    refused(capsys, ["reproduce", "--out", out, "--wam", MINI / "wm_plain"], "'wm-predictor' checkpoint",
            "not a WAM")
    refused(capsys, ["reproduce", "--out", out, "--wam", "checkpoints/stack-cube/tinywam"],
            "made for task 'stack-cube'", "--task stack-cube")
    refused(capsys, ["reproduce", "--out", MINI / "tinywam"], "is not a reproduce directory")
    monkeypatch.setenv("WAMPLAN_DINOV3_PATH", str(tmp_path / "no_weights"))  # the paper preset's, not shipped
    line = refused(capsys, ["reproduce", "--preset", "paper", "--out", out], "--preset paper: dinov3",
                   "no_weights", "set WAMPLAN_DINOV3_PATH=DIR")
    assert "--encoder-path" not in line  # an option reproduce does not have
    assert not out.exists() and not (MINI / "tinywam" / "data").exists()  # nothing started, nothing written


def test_serve_on_a_busy_port_announces_nothing(capsys):
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        for argv, banner in ((["wam", "serve", "--ckpt", MINI / "tinywam"], "serving"),
                             (["serve", "--upstream", MINI / "tinywam", "--world-model", MINI / "wm_augmented"],
                              "planning proxy")):  # the proxy: refused before its models load
            refused(capsys, [*argv, "--port", port], f"127.0.0.1:{port}", "pick another --port")
            assert banner not in refused.out


def test_env_check_names_a_broken_vk_icd_filenames(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("VK_ICD_FILENAMES", str(tmp_path / "nosuch_icd.json"))
    refused(capsys, ["env", "check"], "VK_ICD_FILENAMES=", "nosuch_icd.json does not exist", "unset it")
    (tmp_path / "bad_icd.json").write_text("{not json")
    monkeypatch.setenv("VK_ICD_FILENAMES", str(tmp_path / "bad_icd.json"))
    refused(capsys, ["env", "check"], "VK_ICD_FILENAMES=", "cannot be read as JSON")


def test_an_option_another_command_names_otherwise_is_answered_with_this_commands_name(tmp_path, capsys):
    refused(capsys, ["serve", "--wam", MINI / "tinywam", "--world-model", MINI / "wm_augmented"],
            "unrecognized arguments: --wam; this command names it --upstream")
    refused(capsys, ["wm", "eval", "--wm", MINI / "wm_augmented", "--data", tmp_path],  # not "--ckpt is required"
            "unrecognized arguments: --wm; this command names it --ckpt")
    refused(capsys, ["wam", "serve", "--wam", MINI / "tinywam"], "this command names it --ckpt")
    refused(capsys, ["eval", "--ckpt", "x", "--out", tmp_path / "e"], "this command names it --wam or --wm-augmented")
    refused(capsys, ["wam", "serve", "--ckpt", "x", "--max-request-bytes", "5"],
            "this command names it --max-request-mb (in its own units)")


def test_report_of_a_condition_the_run_does_not_hold(tmp_path, capsys):
    from wamplan.evaluation.records import append_record

    run = tmp_path / "run"
    run.mkdir()
    append_record(run, dict(condition=1, seed=0, variant="open-loop", success=False, outcome="failure", length=10))
    refused(capsys, ["report", tmp_path / "joined", f"{run}:5"], f"{run}:5", "no records of condition(s) [5]", "it has 1")
    (run / "records.jsonl").write_text('{"condition": 1, "seed": 1, "success": true, "outcome": "success"}\n')
    refused(capsys, ["report", run], "record 1 lacks length", "`wamplan eval` writes")  # hand-written: no length


# --------------------------------------------------------------------------------------------- the parser
def test_argparse_errors_print_one_short_usage_line(capsys):
    for argv, said in ((["eval", "--out", "x", "--bogus"], "unrecognized arguments: --bogus"),
                       (["eval", "--first-chunk", "nope"], "invalid choice: 'nope'"),
                       (["eval", "--cost-name", "nope"], "invalid choice: 'nope'"),
                       (["eval", "--wam-profile", "nope"], "cosmos-robocasa"),
                       (["collect", "--source", "expert"], "required: --episodes, --out"),
                       (["wm", "train", "--data", "d", "--out", "o", "--encoder-kwargs", "{}", "--encoder-kwargs",
                         "{}"], "--encoder-kwargs given twice; give it once")):
        with pytest.raises(SystemExit) as e:
            main(argv)
        err = capsys.readouterr().err
        assert e.value.code == 2 and said in err
        assert len(err.strip().splitlines()) == 2  # usage: wamplan eval [options] ..., then the error
        assert err.startswith("usage: wamplan ") and "[options]" in err and "--help" in err.splitlines()[0]


def test_every_option_has_help_and_the_cli_has_a_version(capsys):
    from wamplan.cli.main import iter_commands

    bare, twice = [], []
    for parser in iter_commands():
        for a in parser._actions:
            if isinstance(a, (argparse._HelpAction, argparse._SubParsersAction)) or a.help == argparse.SUPPRESS:
                continue
            text = (a.help or "").strip().replace("%(default)s", str(a.default))  # as argparse prints it
            if not text or re.fullmatch(r"\(default: .*\)", text):
                bare.append(f"{parser.prog} {'/'.join(a.option_strings) or a.dest}")
            if "(default: )" in text or text.count("(default") > 1:  # an empty default, or one said twice
                twice.append(f"{parser.prog} {'/'.join(a.option_strings)}: {text}")
    assert not bare and not twice, twice
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.startswith("wamplan 0.")


def test_training_help_shows_each_presets_default_and_a_held_out_share_outside_0_1_is_refused(expert_store, tmp_path,
                                                                                              capsys):
    from wamplan.cli.main import iter_commands

    helps = {p.prog: {a.dest: a.help for a in p._actions} for p in iter_commands()}
    assert helps["wamplan wm train"]["epochs"].endswith("(default: the preset's, mini 4, paper 24)")
    assert helps["wamplan wm train-decoder"]["batch_size"].endswith("(default: the preset's, mini 32, paper 16)")
    assert helps["wamplan wm train"]["grad_clip"].endswith("(default: 1.0)")  # the same in every preset
    for cmd in ("train", "train-decoder"):
        refused(capsys, ["wm", cmd, "--data", expert_store, "--out", tmp_path / cmd, "--val-fraction", "1"],
                "--val-fraction 1.0", "must be in (0, 1)")
    refused(capsys, ["wm", "train", "--data", expert_store, "--out", tmp_path / "ft", "--init", tmp_path / "gone"],
            "--init", "gone does not exist")  # before the stores are encoded
    assert not (tmp_path / "ft").exists()
    refused(capsys, ["wm", "probe", "--data", expert_store, "--near-mm", "-5"], "--near-mm must be > 0")

def test_help_is_cached_and_matches_argparse(tmp_path, monkeypatch, capsys):
    """`wamplan eval --help` (and --help-all) is built once (imports the planners) and then read from the cache."""
    from wamplan.cli import build_parser

    monkeypatch.setenv("WAMPLAN_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("COLUMNS", "100")
    for _ in range(2):
        with pytest.raises(SystemExit):
            main(["eval", "--help"])
        text = capsys.readouterr().out
        assert list(tmp_path.glob("help/*.json"))
        assert "--wm-augmented WM_AUGMENTED" in text and "--render-backend" not in text
        with pytest.raises(SystemExit):
            main(["eval", "--help-all"])
        text = capsys.readouterr().out
        assert "--first-chunk {open-loop,rest-history}" in text and "--render-backend" in text
    with pytest.raises(SystemExit):
        build_parser().parse_args(["report", "--help"])
    assert "evaluation directory" in capsys.readouterr().out


def test_cached_help_answers_only_for_the_sources_it_was_built_from(tmp_path, monkeypatch, capsys):
    """The cache is stamped with the package's sources (each file's path, size and modification time): a cache of
    other sources is built again rather than printed, and any source file added or modified changes the stamp."""
    import importlib
    import os

    cli_main = importlib.import_module("wamplan.cli.main")  # the module (the package's `main` is its function)

    monkeypatch.setenv("WAMPLAN_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("COLUMNS", "100")

    def eval_help() -> str:
        with pytest.raises(SystemExit):
            main(["eval", "--help"])
        return capsys.readouterr().out

    built = eval_help()
    [path] = (tmp_path / "cache").glob("help/*.json")
    cached = json.loads(path.read_text())
    cached["help"] = {key: "the cached text\n" for key in cached["help"]}
    path.write_text(json.dumps(cached))
    assert eval_help() == "the cached text\n"  # these sources: the cache answers
    path.write_text(json.dumps(dict(cached, stamp="other sources")))
    assert eval_help() == built  # other sources: built again ...
    assert json.loads(path.read_text())["stamp"] == cached["stamp"]  # ... and cached for these

    pkg = tmp_path / "pkg"  # a package of two sources in the place of wamplan's
    (pkg / "cli").mkdir(parents=True)
    (pkg / "cli" / "main.py").write_text("")
    (pkg / "x.py").write_text("a = 1\n")
    monkeypatch.setattr(cli_main, "__file__", str(pkg / "cli" / "main.py"))
    stamps = [cli_main._help_cache()[1]]
    os.utime(pkg / "x.py", ns=(0, 10**9))  # modified: another time
    stamps.append(cli_main._help_cache()[1])
    (pkg / "x.py").write_text("a = 10\n")
    os.utime(pkg / "x.py", ns=(0, 10**9))  # modified: another size
    stamps.append(cli_main._help_cache()[1])
    (pkg / "y.py").write_text("")  # added
    stamps.append(cli_main._help_cache()[1])
    assert len(set(stamps)) == 4 and cli_main._help_cache()[1] == stamps[-1]
