"""`wamplan data export --format cosmos-policy`: the files are read back with h5py and every array is compared
with the store (keys, shapes, dtypes, values)."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from wamplan.cli import main
from wamplan.data.export import DEMO_VIEWS, ROLLOUT_VIEWS, CosmosExportConfig, view_names
from wamplan.data.store import EpisodeStore
from wamplan.envs.contract import CUBE_INSERTION
from wamplan.errors import UserError

DEMO_CAMERAS = dict(zip(CUBE_INSERTION.cameras, DEMO_VIEWS))  # front, side, wrist -> RoboCasa's left, right, wrist
ROLLOUT_CAMERAS = dict(zip(CUBE_INSERTION.cameras, ROLLOUT_VIEWS))
from wamplan.wam.cosmos_client import resize_image

STEPS = 12  # a truncated episode is enough for the layout: 13 frames with every step's views


@pytest.fixture(scope="module")
def dense_store(tmp_path_factory):
    """Expert seeds 0 and 1 at 64 px with views at every step, cut at 12 steps (about 12 s)."""
    root = tmp_path_factory.mktemp("dense") / "store"
    assert main(["collect", "--source", "expert", "--episodes", "2", "--out", str(root), "--camera-size", "64",
                 "--image-every", "1", "--max-steps", str(STEPS)]) == 0
    return root


def _tree(f: h5py.File) -> dict[str, tuple]:
    out = {}
    f.visititems(lambda name, o: out.__setitem__(name, (o.shape, o.dtype) if isinstance(o, h5py.Dataset) else "group"))
    return out


def test_demos_read_back_equal_the_store(dense_store, tmp_path, capsys):
    out = tmp_path / "cosmos"
    assert main(["data", "export", "--format", "cosmos-policy", str(dense_store), str(out), "--split", "demos",
                 "--image-size", "0"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert (summary["demos"], summary["rollouts"], summary["demo_steps"]) == (2, 0, 2 * (STEPS + 1))
    store = EpisodeStore(dense_store)
    eps = [store.load(p) for p in store.episode_paths()]
    with h5py.File(out / "demos" / "wamplan_demos.hdf5", "r") as f:
        n = STEPS + 1
        want = {"data": "group"}
        for i in range(2):
            want.update({f"data/demo_{i}": "group", f"data/demo_{i}/obs": "group",
                         f"data/demo_{i}/actions": ((n, 5), np.float32),
                         f"data/demo_{i}/robot_states": ((n, 10), np.float32),
                         **{f"data/demo_{i}/obs/{k}": ((n, 64, 64, 3), np.uint8) for k in DEMO_CAMERAS.values()}})
        assert _tree(f) == want
        assert f["data"].attrs["total"] == 2 * n
        for i, ep in enumerate(eps):
            g = f[f"data/demo_{i}"]
            assert dict(g.attrs) == dict(task_description=CUBE_INSERTION.instruction, num_samples=n,
                                         wamplan_seed=ep.seed, wamplan_source="expert", success=ep.success,
                                         outcome=ep.outcome, wamplan_padded_actions=1)
            np.testing.assert_array_equal(g["actions"][:STEPS], ep.actions)
            np.testing.assert_array_equal(g["actions"][STEPS], [0, 0, 0, 0, ep.actions[-1, 4]])  # the no-op pad
            np.testing.assert_array_equal(g["robot_states"][:], ep.proprio)
            for cam in store.cameras:
                np.testing.assert_array_equal(g["obs"][DEMO_CAMERAS[cam]][:], ep.images[cam])


def test_rollouts_read_back_at_224_px_as_the_client_sends_them(dense_store, tmp_path):
    out = tmp_path / "cosmos"
    assert main(["data", "export", "--format", "cosmos-policy", str(dense_store), str(out)]) == 0
    assert not list((out / "demos").glob("*.hdf5"))  # no demo: no (empty) demo file for the trainer to trip on
    store = EpisodeStore(dense_store)
    n = STEPS + 1
    for p in store.episode_paths():
        ep = store.load(p)
        assert not ep.success  # cut at 12 steps: auto puts failed episodes in rollout files
        with h5py.File(out / "rollouts" / f"expert-s{ep.seed:07d}.hdf5", "r") as f:
            assert _tree(f) == {"actions": ((n, 5), np.float32), "proprio": ((n, 10), np.float32),
                                **{k: ((n, 224, 224, 3), np.uint8) for k in ROLLOUT_CAMERAS.values()}}
            assert (f.attrs["task_description"], bool(f.attrs["success"]), f.attrs["wamplan_seed"]) == \
                (CUBE_INSERTION.instruction, False, ep.seed)
            np.testing.assert_array_equal(f["actions"][:STEPS], ep.actions)
            np.testing.assert_array_equal(f["proprio"][:], ep.proprio)
            for cam in store.cameras:
                got = f[ROLLOUT_CAMERAS[cam]][:]
                for t in (0, STEPS):  # the frames the /act client would send for the same views
                    np.testing.assert_array_equal(got[t], resize_image(ep.images[cam][t], 224))


def test_a_sparse_store_is_refused_with_the_fix(expert_store, tmp_path, capsys):
    assert main(["data", "export", "--format", "cosmos-policy", str(expert_store), str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "stores views every 4 steps" in err and "--image-every 1" in err
    assert not (tmp_path / "o").exists()


def test_an_existing_export_is_not_overwritten(dense_store, tmp_path, capsys):
    out = tmp_path / "cosmos"
    assert main(["data", "export", "--format", "cosmos-policy", str(dense_store), str(out)]) == 0
    capsys.readouterr()
    assert main(["data", "export", "--format", "cosmos-policy", str(dense_store), str(out)]) == 2
    assert "holds an export already" in capsys.readouterr().err
    ckpt = tmp_path / "ckpt"  # another kind of directory: nothing is added to it
    ckpt.mkdir()
    (ckpt / "config.json").write_text("{}")
    assert main(["data", "export", "--format", "cosmos-policy", str(dense_store), str(ckpt)]) == 2
    assert f"{ckpt} exists and is not empty (config.json); choose a new or empty OUT" in capsys.readouterr().err
    assert sorted(e.name for e in ckpt.iterdir()) == ["config.json"]


def test_export_defaults_match_the_client():
    assert CosmosExportConfig().instruction == ""  # the store's task's instruction (what a WAM of the task is sent)
    with pytest.raises(ValueError, match="--split"):
        CosmosExportConfig(split="train")
    assert view_names(CUBE_INSERTION.cameras, ROLLOUT_VIEWS) == ROLLOUT_CAMERAS
    with pytest.raises(UserError, match="holds 3 views"):
        view_names(("base_camera", "hand_camera"), DEMO_VIEWS)
