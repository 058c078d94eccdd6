"""The encoder probe: ridge recovers a known linear map, and reports mm on a tiny real store."""

import json

import numpy as np
import pytest

from wamplan.cli import main
from wamplan.data.alignment import hole_position
from wamplan.data.store import EpisodeStore
from wamplan.encoders.probe import TARGETS, ProbeData, probe_arrays, split_episodes


def _synthetic(n_eps=12, per=50, dim=40, seed=0):
    rng = np.random.default_rng(seed)
    m = n_eps * per
    feats = {v: rng.standard_normal((m, dim)).astype(np.float32) for v in ("front", "side", "wrist")}
    feats["all"] = np.concatenate([feats[v] for v in ("front", "side", "wrist")], 1)
    w = rng.standard_normal((dim, 3)) * 0.01  # metres per feature
    y = {"cube-rel-tcp": (feats["front"] @ w + 0.1).astype(np.float32),  # seen by the front view only
         "cube-rel-hole": (feats["wrist"] @ w).astype(np.float32)}  # seen by the wrist view only
    return ProbeData(feats, y, np.repeat(np.arange(n_eps), per), [f"src:{i}" for i in range(n_eps)])


def test_probe_recovers_a_linear_relation_only_where_it_exists():
    rep = probe_arrays(_synthetic())
    rows = {(r["view"], r["target"]): r for r in rep["rows"]}
    assert len(rows) == 4 * len(TARGETS)  # three views and all
    for view, target in (("front", "cube-rel-tcp"), ("all", "cube-rel-tcp"), ("wrist", "cube-rel-hole"),
                         ("all", "cube-rel-hole")):
        assert rows[view, target]["error_mm"] < 0.01 < 50 < rows[view, target]["baseline_mm"]
    for view, target in (("side", "cube-rel-tcp"), ("wrist", "cube-rel-tcp"), ("front", "cube-rel-hole")):
        r = rows[view, target]  # unrelated features: no better than the mean
        assert r["error_mm"] > 0.95 * r["baseline_mm"]
    assert rep["episodes"] == {"fit": 9, "held_out": 3} and rep["frames"] == {"fit": 450, "held_out": 150}
    data = _synthetic()
    test = split_episodes(data.episodes, 0.25)[data.episode]
    near = (np.linalg.norm(data.targets["cube-rel-hole"][test, :2], axis=1) < 0.02).sum()
    assert 0 < near < 150 and all(r["near_frames"] == near for r in rep["rows"])
    assert rows["wrist", "cube-rel-hole"]["near_error_mm"] < 0.01  # exact on the near frames too


def test_episode_split_is_stable_and_never_empty():
    names = [f"expert:{i}" for i in range(10)]
    held = split_episodes(names, 0.25)
    assert held.sum() == 3 and np.array_equal(held, split_episodes(list(names), 0.25))
    assert split_episodes(names[:2], 0.01).sum() == 1 and split_episodes(names[:2], 0.99).sum() == 1


@pytest.fixture(scope="module")
def tiny_store(tmp_path_factory):
    root = tmp_path_factory.mktemp("probe") / "expert"
    assert main(["collect", "--source", "expert", "--episodes", "2", "--max-steps", "40", "--out", str(root),
                 "--camera-size", "64"]) == 0
    return root


def test_probe_reports_mm_on_a_real_store_for_two_encoder_settings(tiny_store, tmp_path):
    out = tmp_path / "probe.json"
    kw = ['{"input_size": 32, "patch_size": 16}', '{"input_size": 32, "patch_size": 8}']
    assert main(["wm", "probe", "--data", str(tiny_store), "--encoder", "patch-pixels", "--encoder-kwargs", kw[0],
                 "--encoder-kwargs", kw[1], "--json", str(out)]) == 0
    reports = json.loads(out.read_text())
    assert [r["tokens"][0] for r in reports] == [4, 16]
    store = EpisodeStore(tiny_store)
    eps = [store.load(p) for p in store.episode_paths()]
    held = split_episodes([f"{e.source}:{e.seed}" for e in eps], 0.25)
    fit, test = eps[int(np.flatnonzero(~held)[0])], eps[int(np.flatnonzero(held)[0])]
    for rep in reports:
        assert rep["episodes"] == {"fit": 1, "held_out": 1}
        assert rep["frames"] == {"fit": len(fit.image_steps), "held_out": len(test.image_steps)}
        for target, rel in (("cube-rel-tcp", lambda e: e.tcp_pose[e.image_steps, :3]),
                            ("cube-rel-hole", lambda e: hole_position(store.env)[None])):
            y_fit = fit.cube_pose[fit.image_steps, :3] - rel(fit)
            y_test = test.cube_pose[test.image_steps, :3] - rel(test)
            base = 1000 * np.linalg.norm(y_test - y_fit.mean(0), axis=1).mean()  # the mean baseline, by hand
            for r in (r for r in rep["rows"] if r["target"] == target):
                assert r["baseline_mm"] == pytest.approx(base, rel=1e-4)
                assert np.isfinite(r["error_mm"]) and 0 <= r["error_mm"] < 1e4
