"""Episode store, collection (resume, kill -9), readers (shapes and action-block alignment), errors."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from wamplan.cli import main
from wamplan.data.readers import H5Cache, WAMSamples, WorldModelWindows, open_file_budget, split_of
from wamplan.data.store import EpisodeStore, StoreError, reading
from wamplan.envs.contract import CAMERAS, CUBE_INSERTION

SMALL = ["--camera-size", "64"]


@pytest.fixture(scope="module")
def store(tmp_path_factory, expert_store):
    """The session's two expert episodes (copied: these tests add to the store) plus two short pink ones."""
    root = tmp_path_factory.mktemp("store") / "expert"
    shutil.copytree(expert_store, root)
    assert main(["collect", "--source", "pink", "--episodes", "2", "--seed-start", "10", "--max-steps", "30",
                 "--out", str(root), *SMALL]) == 0
    return root


def test_store_contents(store):
    s = EpisodeStore(store)
    metas = list(s.iter_meta())
    assert sorted((m["source"], m["seed"]) for m in metas) == [("expert", 0), ("expert", 1), ("pink", 10), ("pink", 11)]
    for m in metas:
        ep = s.load(m["path"])
        T = ep.length
        assert ep.actions.shape == (T, 5) and ep.proprio.shape == (T + 1, 10) and ep.stages.shape == (T + 1, 5)
        assert ep.sim_state.shape[0] == T + 1 and ep.drive_targets.shape == (T + 1, 9)
        assert ep.image_steps[0] == 0 and ep.image_steps[-1] == T
        assert all(t % 4 == 0 for t in ep.image_steps[:-1])
        for c in CAMERAS:
            assert ep.images[c].shape == (len(ep.image_steps), 64, 64, 3) and ep.images[c].dtype == np.uint8
        assert ep.provenance["wamplan_version"] and ep.policy["name"] == m["source"]
    expert = [m for m in metas if m["source"] == "expert"]
    assert all(m["success"] for m in expert)
    assert all(m["length"] == 30 and not m["success"] for m in metas if m["source"] == "pink")


def test_stored_images_match_rerender(store, small_env):
    """The stored sim state restores the scene: re-rendering it gives the stored picture."""
    s = EpisodeStore(store)
    ep = s.load(s.episode_path("expert", 1))
    e = small_env  # 64 px, as the store
    e.reset(1)
    k = 5
    t = ep.image_steps[k]
    import torch

    e.base.set_state(torch.as_tensor(ep.sim_state[t][None]))
    views = e.render()
    for c in ("front", "side"):
        diff = np.abs(views[c].astype(int) - ep.images[c][k].astype(int))
        assert diff.mean() < 2.0, (c, diff.mean())


def test_resume_skips_finished(store, capsys):
    assert main(["collect", "--source", "expert", "--episodes", "2", "--out", str(store), *SMALL]) == 0
    out = capsys.readouterr().out
    assert "already in" in out and '"collected": 0' in out


def test_incompatible_settings_rejected(store, capsys):
    rc = main(["collect", "--source", "expert", "--episodes", "1", "--out", str(store), "--camera-size", "96"])
    err = capsys.readouterr().err
    assert rc == 2 and "other env settings" in err and "camera_size" in err
    rc = main(["collect", "--source", "expert", "--episodes", "1", "--out", str(store), "--image-every", "2", *SMALL])
    assert rc == 2 and "images every 4 steps" in capsys.readouterr().err


def test_store_records_its_task(store):
    s = EpisodeStore(store)
    assert s.manifest["task"] == CUBE_INSERTION.describe() and s.task == CUBE_INSERTION
    assert s.cameras == CUBE_INSERTION.cameras and s.env["task"] == "cube-insertion"


def test_stack_cube_stores_record_both_cubes_and_the_tcp(tmp_path):
    """StackCube-v1's privileged poses: the cube to pick (``cube_pose``), the cube it goes on (``target_pose``)."""
    out = tmp_path / "stack"
    assert main(["collect", "--task", "stack-cube", "--source", "pink", "--episodes", "1", "--max-steps", "8",
                 *SMALL, "--out", str(out)]) == 0
    path = next((out / "episodes").glob("*.h5"))
    with h5py.File(path, "r") as f:
        a, b, tcp = f["cube_pose"][:, :3], f["target_pose"][:, :3], f["tcp_pose"][:, :3]  # (T+1, 3) each
    assert a.shape == b.shape == tcp.shape == (9, 3) and 0.02 < np.linalg.norm(a[0, :2] - b[0, :2]) < 0.5  # apart


def test_a_store_that_records_no_task_is_the_cube_tasks(expert_store, tmp_path, capsys):
    """A store written before tasks (no ``task`` in its manifest or env settings) holds cube-insertion episodes:
    collecting resumes it, and another task's collection is refused in one line naming both tasks."""
    legacy = tmp_path / "legacy"
    shutil.copytree(expert_store, legacy)
    man = json.loads((legacy / "store.json").read_text())
    del man["task"], man["env"]["task"]
    (legacy / "store.json").write_text(json.dumps(man))
    s = EpisodeStore(legacy)
    assert s.task == CUBE_INSERTION and s.cameras == CUBE_INSERTION.cameras
    assert s.env == EpisodeStore(expert_store).env
    assert main(["collect", "--source", "expert", "--episodes", "2", "--out", str(legacy), *SMALL]) == 0
    assert '"collected": 0' in capsys.readouterr().out
    rc = main(["collect", "--source", "pink", "--episodes", "1", "--out", str(legacy), "--task", "push-cube", *SMALL])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "'cube-insertion'" in err and "'push-cube'" in err


def test_a_policy_that_cannot_act_in_the_task_writes_nothing(tmp_path, capsys):
    out = tmp_path / "peg"
    rc = main(["collect", "--source", "expert", "--episodes", "1", "--out", str(out), "--task", "peg-insertion-side"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "no scripted expert" in err and not out.exists()


def test_collect_given_seeds_resumes_by_seed(tmp_path):
    from wamplan.data.collect import collect
    from wamplan.envs.config import EnvConfig

    out = tmp_path / "pink"
    kw = dict(max_steps=4, env=EnvConfig(camera_size=64), progress=False, log=lambda *a: None)
    assert collect("pink", 2, out, seeds=[7, 3], **kw)["collected"] == 2
    assert EpisodeStore(out).finished_seeds("pink") == {3, 7}
    s = collect("pink", 2, out, seeds=[3, 12], **kw)
    assert (s["collected"], s["skipped"]) == (1, 1) and EpisodeStore(out).finished_seeds("pink") == {3, 7, 12}
    assert collect("pink", 0, out, seeds=[], **kw)["collected"] == 0


def test_collect_passes_expert_settings(tmp_path, capsys):
    """--expert-* / --noisy-* reach the policy the workers build (the store records them), and a setting of
    another source is refused before anything is written."""
    out = tmp_path / "noisy"
    assert main(["collect", "--source", "noisy-expert", "--episodes", "1", "--max-steps", "8", "--out", str(out),
                 "--expert-turn-in", "approach", "--noisy-noise-std", "0.05", *SMALL]) == 0
    (meta,) = EpisodeStore(out).iter_meta()
    policy = EpisodeStore(out).load(meta["path"]).policy
    assert policy["noise_std"] == 0.05 and policy["expert"]["turn_in"] == "approach"
    assert policy["expert"]["align_tol"] == 0.003  # not given: the default
    capsys.readouterr()
    rc = main(["collect", "--source", "pink", "--episodes", "1", "--out", str(tmp_path / "pink"),
               "--expert-gain", "0.5", *SMALL])
    assert rc == 2 and "--expert-gain: not a setting of --source pink" in capsys.readouterr().err
    assert not (tmp_path / "pink").exists()


def test_world_model_windows_alignment(store):
    ds = WorldModelWindows([store], frameskip=4, history=3, horizon=2, split="all")
    s = EpisodeStore(store)
    assert len(ds) > 10
    for idx in (0, len(ds) // 2, len(ds) - 1):
        item = ds[idx]
        i, k = ds.items[idx]
        ep = s.load(ds.episodes[i].path)
        steps = item["steps"].numpy()
        assert np.all(np.diff(steps) == 4) and item["q"].shape == (5, 10) and item["a"].shape == (5, 20)
        assert item["images"].shape == (5, 3, 64, 64, 3)
        for j, t in enumerate(steps):
            np.testing.assert_array_equal(item["a"][j].numpy(), ep.actions[t:t + 4].reshape(-1))
            np.testing.assert_array_equal(item["q"][j].numpy(), ep.proprio[t])
            kk = list(ep.image_steps).index(t)
            for v, c in enumerate(CAMERAS):
                np.testing.assert_array_equal(item["images"][j, v].numpy(), ep.images[c][kk])


def test_wam_samples_alignment(store):
    ds = WAMSamples([store], chunk=16, split="all", sources=["expert"])
    s = EpisodeStore(store)
    for idx in (0, len(ds) - 1):
        item = ds[idx]
        ep = s.load(ds.episodes[ds.items[idx][0]].path)
        t = int(item["step"])
        t_end = min(t + 16, ep.length)
        n = t_end - t
        np.testing.assert_array_equal(item["actions"][:n].numpy(), ep.actions[t:t_end])
        assert np.all(item["actions"][n:].numpy() == ep.actions[t_end - 1])  # held past the end
        kk = list(ep.image_steps).index(t_end)
        np.testing.assert_array_equal(item["future"][2].numpy(), ep.images["wrist"][kk])
        np.testing.assert_array_equal(item["proprio"].numpy(), ep.proprio[t])


def test_split_is_stable_and_disjoint(store):
    tr = {(e.source, e.seed) for e in WorldModelWindows([store], split="train", val_fraction=0.5).episodes}
    va = {(e.source, e.seed) for e in WorldModelWindows([store], split="val", val_fraction=0.5).episodes}
    assert not tr & va and len(tr | va) == 4
    assert split_of("expert", 3, 0.1) == split_of("expert", 3, 0.1)
    frac = np.mean([split_of("noisy-expert", s, 0.1) == "val" for s in range(2000)])
    assert 0.07 < frac < 0.13


def test_foreign_and_damaged_dirs(tmp_path, capsys, store):
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("hello")
    assert main(["data", "info", str(foreign)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "not a wamplan episode store" in err
    assert main(["collect", "--source", "expert", "--episodes", "1", "--out", str(foreign)]) == 2
    assert "not a wamplan episode store" in capsys.readouterr().err
    assert (foreign / "notes.txt").read_text() == "hello"  # nothing lost
    # a damaged episode file
    broken = tmp_path / "broken"
    shutil.copytree(store, broken)
    victim = sorted((broken / "episodes").glob("*.h5"))[0]
    victim.write_bytes(b"\x00garbage")
    assert main(["data", "info", str(broken)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "damaged" in err and victim.name in err
    (broken / "store.json").write_text("{not json")
    assert main(["data", "info", str(broken)]) == 2
    assert "damaged" in capsys.readouterr().err


def test_info_and_view(store, tmp_path, capsys):
    assert main(["data", "info", str(store), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["episodes"] == 4 and info["sources"]["expert"]["success_rate"] == 1.0
    assert info["sources"]["pink"]["outcomes"] == {"never_lifted": 2} and info["bytes_per_episode"] > 0
    assert main(["data", "view", str(store), "--episode", "0", "--out", str(tmp_path / "s.png")]) == 0
    import imageio.v3 as iio

    assert iio.imread(tmp_path / "s.png").ndim == 3
    assert main(["data", "view", str(store), "--episode", "99"]) == 2
    assert "out of range" in capsys.readouterr().err
    for n in ("0", "-2"):
        assert main(["data", "view", str(store), "--frames", n, "--out", str(tmp_path / "z.png")]) == 2
        assert f"--frames {n}: a contact sheet needs at least 1 frame" in capsys.readouterr().err


@pytest.mark.parametrize("workers", [1, pytest.param(2, marks=pytest.mark.slow)])
def test_kill9_then_resume(tmp_path, capsys, workers):
    """kill -9 the whole collection (parent and any workers) mid-run; resuming completes it exactly.
    One process by default; the two-worker run (three interpreters to start) is in the slow suite."""
    out = tmp_path / "pink"
    args = ["collect", "--source", "pink", "--episodes", "6", "--max-steps", "12", "--workers", str(workers),
            "--out", str(out), *SMALL]
    proc = subprocess.Popen([sys.executable, "-m", "wamplan.cli", *args], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 240
    while time.time() < deadline and len(list((out / "episodes").glob("[!.]*.h5"))) < 2:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    before = {p.name: p.read_bytes() for p in (out / "episodes").glob("[!.]*.h5")}
    assert 2 <= len(before) < 6, "the kill should land mid-collection"
    capsys.readouterr()
    assert main(args) == 0  # resume in-process
    s = EpisodeStore(out)
    assert s.finished_seeds("pink") == set(range(6))
    assert len(s.episode_paths()) == 6 and not list((out / "episodes").glob(".tmp-*"))
    for name, data in before.items():  # finished episodes are untouched
        assert (out / "episodes" / name).read_bytes() == data
    for p in s.episode_paths():
        assert s.load(p).length == 12
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["collected"] == 6 - len(before)


def test_feature_cache_feeds_windows(store):
    from wamplan.data.features import encode_store, feature_dir, feature_key
    from wamplan.encoders import make_encoder

    enc = make_encoder("patch-pixels")
    key = feature_key(enc.config_dict())
    done = list(encode_store(store, enc))
    assert len(done) == 4 and list(encode_store(store, enc)) == []  # cached: a second pass encodes nothing
    assert len(list(feature_dir(store, key).glob("*.h5"))) == 4
    ds = WorldModelWindows([store], split="all", features=key)
    item = ds[7]
    assert item["z"].shape == (5, 3, enc.num_patches, enc.dim) and item["z"].dtype.is_floating_point
    # the cached features are the encoder's features of the stored frames
    raw = WorldModelWindows([store], split="all")[7]["images"]  # (T, V, H, W, 3)
    ref = enc.encode(raw[2].reshape(-1, *raw.shape[2:])).reshape(3, enc.num_patches, enc.dim)
    assert (item["z"][2].float() - ref).abs().max() < 2e-2  # float16 rounding


def test_windows_without_cache_say_how_to_make_it(store):
    with pytest.raises(StoreError, match="wamplan wm encode"):
        WorldModelWindows([store], split="all", features="dinov3-vitl16")


def test_feature_cache_is_keyed_by_the_whole_encoder_config(store, tmp_path):
    """Another input size (same encoder name) gets its own cache; a file of another encoder under a key is refused."""
    import shutil

    from wamplan.data.features import encode_store, feature_dir, feature_key
    from wamplan.encoders import make_encoder

    root = tmp_path / "store"
    shutil.copytree(store, root)
    a = make_encoder("patch-pixels", input_size=48, patch_size=16)
    b = make_encoder("patch-pixels", input_size=32, patch_size=16)
    ka, kb = feature_key(a.config_dict()), feature_key(b.config_dict())
    assert ka != kb and ka.startswith("patch-pixels-")
    assert len(list(encode_store(root, a))) == 4
    assert len(list(encode_store(root, b))) == 4  # not a silent reuse of a's features
    za = WorldModelWindows([root], split="all", features=ka)[0]["z"]
    zb = WorldModelWindows([root], split="all", features=kb)[0]["z"]
    assert za.shape[-2] == 9 and zb.shape[-2] == 4  # a 3 x 3 and a 2 x 2 grid per view
    # a's file copied into b's cache: the readers and the encoder refuse it with one line
    name = sorted(feature_dir(root, ka).glob("*.h5"))[0].name
    shutil.copy(feature_dir(root, ka) / name, feature_dir(root, kb) / name)
    with pytest.raises(StoreError, match=f"holds features of encoder .* not of '{kb}'; delete") as e:
        WorldModelWindows([root], split="all", features=kb)
    assert "\n" not in str(e.value)
    with pytest.raises(StoreError, match="run `wamplan wm encode` again"):
        list(encode_store(root, b))


def test_windows_may_end_on_the_episodes_last_frame(store):
    """window_end='frame': one more window per episode whose last frame is the last Δ-grid frame (the final,
    e.g. seated, state becomes a prediction target); the unused last block is padded with the last action."""
    kw = dict(split="all", frameskip=4, history=3, horizon=2)
    block, frame = WorldModelWindows([store], **kw), WorldModelWindows([store], window_end="frame", **kw)
    assert len(frame) == len(block) + len(block.episodes)
    last = {}
    for i, k in frame.items:
        last[i] = max(last.get(i, -1), k)
    for i, e in enumerate(frame.episodes):
        item = frame[frame.items.index((i, last[i]))]
        end = int(item["steps"][-1])
        assert end == 4 * (e.length // 4) and end + 4 > e.length  # the last frame on the grid
        ep = EpisodeStore(store).load(e.path)
        np.testing.assert_array_equal(item["q"][-1].numpy(), ep.proprio[end])
        acts = item["a"].numpy().reshape(-1, 5)  # (T·Δ, 5)
        real = ep.actions[int(item["steps"][0]):]
        np.testing.assert_array_equal(acts[:len(real)], real)
        assert (acts[len(real):] == real[-1]).all()


def test_open_files_are_bounded_least_recently_read_closed_first(store):
    """A dataset of more files than the open-file limit reads: the cache closes the least recently read file."""
    paths = sorted(str(p) for p in (store / "episodes").glob("*.h5"))
    assert len(paths) >= 4
    cache = H5Cache(max_open=2)
    lengths = {p: int(cache.get(p).attrs["length"]) for p in paths}
    assert len(cache) == 2
    first = cache.get(paths[0])  # re-opened after it was closed, and still reads
    assert int(first.attrs["length"]) == lengths[paths[0]]
    kept = cache.get(paths[-1])
    cache.get(paths[1])  # evicts paths[0], the least recently read, not paths[-1]
    assert kept.id.valid and not first.id.valid and len(cache) == 2
    assert open_file_budget() >= 16


def _open_in_child(cache, path, out):
    f = cache.get(path)
    out.put((len(cache), int(f.attrs["length"])))


def test_a_forked_worker_opens_its_own_files(store):
    """A DataLoader worker forked after the parent read keeps none of the parent's HDF5 handles."""
    import multiprocessing as mp

    paths = sorted(str(p) for p in (store / "episodes").glob("*.h5"))
    cache = H5Cache(max_open=4)
    parent_file = cache.get(paths[0])
    ctx = mp.get_context("fork")
    out = ctx.Queue()
    child = ctx.Process(target=_open_in_child, args=(cache, paths[1], out))
    child.start()
    opened, length = out.get(timeout=60)
    child.join(timeout=60)
    assert child.exitcode == 0 and opened == 1 and length > 0  # only the file the child opened itself
    assert parent_file.id.valid and len(cache) == 1  # the parent's handle is untouched


def test_an_error_after_the_read_is_not_called_damage(store):
    """Only a failure inside h5py names the file as damaged; a computation's error passes through unchanged."""
    path = sorted((store / "episodes").glob("*.h5"))[0]
    with pytest.raises(RuntimeError, match="not a read"):
        with reading(path):
            with h5py.File(path, "r") as f:
                f["actions"][()]
            raise RuntimeError("not a read")
    with pytest.raises(StoreError, match="is damaged"):
        with reading(path):
            with h5py.File(path, "r") as f:
                f["no such dataset"]


def test_too_many_open_files_is_not_called_damage():
    with pytest.raises(StoreError) as e:
        with reading("ep.h5"):
            raise OSError("Unable to open file (unable to open file: name = 'ep.h5', errno = 24, error message = "
                          "'Too many open files', flags = 0, o_flags = 0)")
    assert "too many open files" in str(e.value) and "not damaged" in str(e.value) and "ulimit -n" in str(e.value)
