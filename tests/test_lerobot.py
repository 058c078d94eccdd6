"""LeRobot datasets in and out: `wamplan data export --format lerobot` read back with pyarrow and PyAV and compared
with the store; export -> import -> export (v2.1) gives the same tables and frames; a dataset laid out as openpi's
LIBERO conversion writes it (image features in the parquet, its key names) imports with a key map; bad input is one
line and leaves no OUT behind."""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from wamplan.cli import main
from wamplan.data.lerobot import layout as L
from wamplan.data.lerobot.video import read_span
from wamplan.data.store import EpisodeStore
from wamplan.envs.spec import TASKS, TaskSpec, register_task

STEPS = 7  # 8 frames an episode: enough for spans, padding and stats
SIZE = 32
CAMS = ("front", "side", "wrist")


def _views(seed: int, steps: int, size: int) -> dict[str, np.ndarray]:
    """Smooth views with a bright square moving a pixel a step (so that a shifted frame shows), per camera."""
    yy, xx = np.mgrid[0:size, 0:size]
    out = {}
    for j, cam in enumerate(CAMS):
        frames = np.zeros((steps + 1, size, size, 3), np.uint8)
        for t in range(steps + 1):
            frames[t, ..., 0], frames[t, ..., 1] = 4 * xx + 20 * j, 4 * yy + 10 * seed
            frames[t, ..., 2] = 60
            x0 = 4 + 2 * t + seed
            frames[t, 8:18, x0:x0 + 10] = 230
        out[cam] = frames
    return out


@pytest.fixture(scope="module")
def dense_store(tmp_path_factory):
    """Two cube-insertion episodes of 7 steps at 32 px with every step's views, made without the simulator."""
    from wamplan.data.store import EpisodeData
    from wamplan.envs.config import EnvConfig

    env = EnvConfig(camera_size=SIZE)
    root = tmp_path_factory.mktemp("lerobot") / "store"
    store = EpisodeStore(root, create=True, env=env.task_kwargs(), image_every=1, task=env.spec)
    rng = np.random.default_rng(0)
    for seed in (0, 1):
        store.write(EpisodeData.logged(env.spec, seed, rng.uniform(-1, 1, (STEPS, 5)), rng.normal(size=(STEPS + 1, 10)),
                                       _views(seed, STEPS, SIZE), range(STEPS + 1), image_every=1, source="expert",
                                       success=bool(seed), outcome="success" if seed else "never_lifted"))
    return root


@pytest.fixture(scope="module")
def v3_export(dense_store, tmp_path_factory):
    out = tmp_path_factory.mktemp("v3") / "ds"
    assert main(["data", "export", "--format", "lerobot", str(dense_store), str(out)]) == 0
    return out


def _frames_match(decoded: np.ndarray, stored: np.ndarray) -> None:
    """Each decoded frame is close to its own stored frame (codec tolerance), closer than to the neighbouring
    frame's (no frame is shifted)."""
    err = np.abs(decoded.astype(float) - stored.astype(float)).mean(axis=(1, 2, 3))  # (N,)
    assert err.max() < 12, err
    shifted = np.abs(decoded[1:].astype(float) - stored[:-1].astype(float)).mean(axis=(1, 2, 3))  # (N-1,)
    assert (err[1:] < shifted).all(), (err, shifted)


def test_v3_export_has_lerobots_files_schema_and_frames(dense_store, v3_export):
    root = v3_export
    keys = [f"observation.images.{c}" for c in CAMS]
    files = {p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file()}
    assert files == {
        "meta/info.json", "meta/stats.json", "meta/tasks.parquet", "meta/wamplan.json",
        "meta/episodes/chunk-000/file-000.parquet", "data/chunk-000/file-000.parquet",
        *(f"videos/{k}/chunk-000/file-000.mp4" for k in keys)}
    listing = [b for b in doc_blocks("Export") if b.startswith("meta/")][0]  # what the doc says an export holds
    assert {line.split()[0] for line in listing.splitlines() if line[:1].isalpha()} == files
    info = json.loads((root / "meta/info.json").read_text())
    n = 2 * (STEPS + 1)
    assert info["codebase_version"] == "v3.0" and info["fps"] == 20 and info["total_frames"] == n
    assert info["total_episodes"] == 2 and info["total_tasks"] == 1
    f = info["features"]
    assert f["action"]["shape"] == [5] and f["action"]["dtype"] == "float32" and f["action"]["names"][4] == "gripper"
    assert f["observation.state"]["shape"] == [10]
    for k in keys:
        assert f[k]["dtype"] == "video" and f[k]["shape"] == [SIZE, SIZE, 3]
        assert f[k]["info"]["video.codec"] in ("av1", "h264") and f[k]["info"]["video.fps"] == 20
    data = pq.read_table(root / "data/chunk-000/file-000.parquet")
    assert data.column_names == ["action", "observation.state", "timestamp", "frame_index", "episode_index", "index",
                                 "task_index"]
    assert data.schema.field("action").type == pa.list_(pa.float32(), 5)
    assert data.column("index").to_pylist() == list(range(n))
    assert data.column("frame_index").to_pylist() == list(range(STEPS + 1)) * 2
    np.testing.assert_allclose(data.column("timestamp").to_numpy()[:STEPS + 1], np.arange(STEPS + 1) / 20, atol=1e-6)
    eps = pq.read_table(root / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    store = EpisodeStore(dense_store)
    tasks = pq.read_table(root / "meta/tasks.parquet").to_pylist()
    assert tasks == [{"task_index": 0, "__index_level_0__": store.task.instruction}]
    actions = L.column_array(data, "action", root)
    state = L.column_array(data, "observation.state", root)
    for e, (ep, path) in enumerate(zip(eps, store.episode_paths())):
        stored = store.load(path)
        lo, hi = ep["dataset_from_index"], ep["dataset_to_index"]
        assert (ep["episode_index"], ep["length"], hi - lo) == (e, STEPS + 1, STEPS + 1)
        assert (ep["wamplan/seed"], ep["wamplan/source"], ep["wamplan/outcome"]) == (stored.seed, "expert",
                                                                                    stored.outcome)
        np.testing.assert_array_equal(actions[lo:hi - 1], stored.actions)
        np.testing.assert_array_equal(actions[hi - 1], [0, 0, 0, 0, stored.actions[-1, 4]])  # the padding no-op
        np.testing.assert_array_equal(state[lo:hi], stored.proprio)
        assert ep["stats/action/count"] == [STEPS + 1] and len(ep["stats/observation.images.front/mean"]) == 3
        for c, k in zip(CAMS, keys):
            assert ep[f"videos/{k}/from_timestamp"] == pytest.approx(lo / 20)
            assert ep[f"videos/{k}/to_timestamp"] == pytest.approx(hi / 20)
            frames = read_span(root / f"videos/{k}/chunk-000/file-000.mp4", ep[f"videos/{k}/from_timestamp"],
                               ep[f"videos/{k}/to_timestamp"], 20, k)
            assert frames.shape == (STEPS + 1, SIZE, SIZE, 3)
            _frames_match(frames, stored.images[c])
    stats = json.loads((root / "meta/stats.json").read_text())
    assert stats["action"]["count"] == [n]
    np.testing.assert_allclose(stats["action"]["mean"], actions.mean(0), atol=1e-5)
    np.testing.assert_allclose(stats["observation.state"]["std"], state.std(0), atol=1e-4)


def test_v21_round_trip_is_identical(dense_store, tmp_path, capsys):
    """export (v2.1) -> import -> export: the same parquet tables and metadata; frames the same to the codec's
    generation loss (a lossy codec re-encodes decoded frames)."""
    a, store, b = tmp_path / "a", tmp_path / "store", tmp_path / "b"
    assert main(["data", "export", "--format", "lerobot", "--lerobot-version", "2.1", str(dense_store), str(a)]) == 0
    assert main(["data", "import", "--format", "lerobot", str(a), str(store), "--task", "cube-insertion",
                 "--camera-size", str(SIZE)]) == 0
    capsys.readouterr()
    assert main(["data", "export", "--format", "lerobot", "--lerobot-version", "2.1", str(store), str(b)]) == 0
    files = sorted(p.relative_to(a).as_posix() for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b).as_posix() for p in b.rglob("*") if p.is_file())
    assert "data/chunk-000/episode_000001.parquet" in files and "meta/episodes.jsonl" in files
    assert "videos/chunk-000/observation.images.wrist/episode_000000.mp4" in files
    for name in files:
        if name.endswith(".parquet"):
            assert pq.read_table(a / name).equals(pq.read_table(b / name)), name
        elif name in ("meta/info.json", "meta/episodes.jsonl", "meta/tasks.jsonl"):
            assert (a / name).read_text() == (b / name).read_text(), name
        elif name.endswith(".mp4"):
            fa, fb = read_span(a / name, 0, None, 20, name), read_span(b / name, 0, None, 20, name)
            assert fa.shape == fb.shape == (STEPS + 1, SIZE, SIZE, 3)
            _frames_match(fb, fa)
    info = json.loads((a / "meta/info.json").read_text())
    assert info["codebase_version"] == "v2.1" and info["total_videos"] == 6
    # the imported store keeps the episodes' identity and every step's views
    s, d = EpisodeStore(store), EpisodeStore(dense_store)
    assert s.image_every == 1 and [m["seed"] for m in s.iter_meta()] == [m["seed"] for m in d.iter_meta()]


def _png(img: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return buf.getvalue()


def _libero_like(root: Path, episodes: int = 2, frames: int = 6, size: int = 48) -> list[dict]:
    """A v2.1 dataset laid out as openpi's LIBERO conversion writes it: image features (PNG bytes in the parquet)
    ``image`` and ``wrist_image``, ``state`` (8,), ``actions`` (7,), fps 10, one parquet file an episode."""
    rng = np.random.default_rng(0)
    feats = {"image": dict(dtype="image", shape=[size, size, 3], names=["height", "width", "channel"]),
             "wrist_image": dict(dtype="image", shape=[size, size, 3], names=["height", "width", "channel"]),
             "state": dict(dtype="float32", shape=[8], names=["state"]),
             "actions": dict(dtype="float32", shape=[7], names=["actions"]), **L.index_features()}
    L.write_json(root / "meta/info.json", {"codebase_version": "v2.1", "robot_type": "panda", "total_episodes": episodes,
                 "total_frames": episodes * frames, "total_tasks": 1, "total_videos": 0, "total_chunks": 1,
                 "chunks_size": 1000, "fps": 10, "splits": {"train": f"0:{episodes}"},
                 "data_path": L.DATA_V2, "video_path": None, "features": feats})
    L.write_jsonl(root / "meta/tasks.jsonl", [{"task_index": 0, "task": "put the bowl on the plate"}])
    L.write_jsonl(root / "meta/episodes.jsonl", [{"episode_index": e, "tasks": ["put the bowl on the plate"],
                                                  "length": frames} for e in range(episodes)])
    made = []
    for e in range(episodes):
        ep = dict(image=rng.integers(0, 255, (frames, size, size, 3), np.uint8),
                  wrist_image=rng.integers(0, 255, (frames, size, size, 3), np.uint8),
                  state=rng.normal(size=(frames, 8)).astype(np.float32),
                  actions=rng.uniform(-1, 1, (frames, 7)).astype(np.float32))
        img = pa.struct([("bytes", pa.binary()), ("path", pa.string())])
        table = pa.table({
            "image": pa.array([{"bytes": _png(x), "path": None} for x in ep["image"]], img),
            "wrist_image": pa.array([{"bytes": _png(x), "path": None} for x in ep["wrist_image"]], img),
            "state": pa.array(ep["state"].tolist(), pa.list_(pa.float32())),
            "actions": pa.array(ep["actions"].tolist(), pa.list_(pa.float32())),
            "timestamp": pa.array(np.arange(frames, dtype=np.float32) / 10), "frame_index": np.arange(frames),
            "episode_index": np.full(frames, e), "index": e * frames + np.arange(frames),
            "task_index": np.zeros(frames, np.int64)})
        (root / "data/chunk-000").mkdir(parents=True, exist_ok=True)
        pq.write_table(table, root / f"data/chunk-000/episode_{e:06d}.parquet")
        made.append(ep)
    return made


DOC = Path(__file__).resolve().parents[1] / "docs" / "lerobot.md"
LIBERO = "Another robot's dataset: openpi's LIBERO set"


def doc_section(title: str) -> str:
    """The text of docs/lerobot.md's section ``## title``."""
    text = DOC.read_text()
    return text[text.index(f"## {title}\n"):].split("\n## ", 1)[0]


def doc_blocks(title: str, lang: str = "") -> list[str]:
    """The ```lang blocks of that section, in order."""
    parts = doc_section(title).split("```")
    return [b[len(lang) + 1:] for b in parts[1::2] if b.startswith(lang + "\n")]


@pytest.fixture
def libero_task():
    """The doc's LIBERO task (its Python block run as written), registered for the test only."""
    code, = doc_blocks(LIBERO, "python")
    exec(compile(code, str(DOC), "exec"), {})
    yield TASKS["libero-panda"]
    TASKS.pop("libero-panda")


def test_the_docs_libero_session_prints_what_it_shows(tmp_path, monkeypatch, libero_task, capsys):
    """docs/lerobot.md's LIBERO session, run on a two-episode stand-in in openpi's layout: the task's line, the
    import report's fields it shows, what training reads of the store, and the refusal of a dataset without the
    key map, word for word."""
    from wamplan.data.export import resize_frames
    from wamplan.data.readers import WAMSamples, WorldModelWindows

    monkeypatch.chdir(tmp_path)
    made = _libero_like(Path("libero"))
    session, = [b for b in doc_blocks(LIBERO) if b.startswith("$ ")]
    commands, outputs = [], []
    for line in session.replace("\\\n    ", "").splitlines():
        (commands if line.startswith("$ ") else outputs).append(line.removeprefix("$ "))
    tasks_line, report_shown = outputs
    assert main(["tasks"]) == 0
    assert tasks_line in capsys.readouterr().out.splitlines()
    argv = commands[1].split()[1:]
    assert main(argv) == 0
    report = json.loads(capsys.readouterr().out)
    for key, value in json.loads(report_shown.replace(', "keys": {...}', "").replace(", ...}", "}")).items():
        assert report[key] == value, key
    store = EpisodeStore("store")
    assert store.task_name == "libero-panda" and store.image_every == 1
    for path, ep in zip(store.episode_paths(), made):
        got = store.load(path)
        assert (got.source, got.outcome, got.length) == ("lerobot", "logged", 5)
        np.testing.assert_array_equal(got.actions, ep["actions"][:5])  # the last frame's action leads nowhere
        np.testing.assert_array_equal(got.proprio, ep["state"])
        np.testing.assert_array_equal(got.images["agentview"], resize_frames(ep["image"], 32))  # PNG is lossless
        np.testing.assert_array_equal(got.images["wrist"], resize_frames(ep["wrist_image"], 32))
    # what `wam train` and `wm train` read
    item = WAMSamples(["store"], chunk=4, split="all")[0]
    assert item["images"].shape == (2, 32, 32, 3) and item["actions"].shape == (4, 7)
    window = WorldModelWindows(["store"], frameskip=1, history=2, horizon=1, split="all")[0]
    assert window["images"].shape == (3, 2, 32, 32, 3)
    assert len(commands) == 3 and main(commands[2].split()[1:]) == 0  # the doc's `wam train` on the store
    assert Path("wamrun").is_dir()
    capsys.readouterr()
    refusal = doc_section(LIBERO).split("refused with `")[1].split("`.)")[0].replace("\n", " ")
    unmapped = [a if a != "store" else "store2" for a in argv[:argv.index("--key-map")]]
    assert main(unmapped) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == f"wamplan: error: {refusal}"


def _break(kind: str, root: Path) -> str:
    """Damage the export at ``root`` one way; returns what the refusal must name."""
    if kind == "not-lerobot":
        (root / "meta/info.json").unlink()
        return "meta/info.json is missing"
    if kind == "version":
        info = json.loads((root / "meta/info.json").read_text())
        (root / "meta/info.json").write_text(json.dumps(dict(info, codebase_version="v9.9")))
        return "codebase_version 'v9.9' is not a LeRobot version"
    if kind == "video":
        (root / "videos/observation.images.side/chunk-000/file-000.mp4").unlink()
        return "observation.images.side/chunk-000/file-000.mp4 is missing"
    data = root / "data/chunk-000/file-000.parquet"  # frames: one row fewer than the episodes metadata says
    pq.write_table(pq.read_table(data).slice(1), data)
    return "file-000.parquet: episode 0 has 7 rows, but the episodes metadata gives it 8 frames"


KINDS = ["not-lerobot", "version", "video", "frames"]  # in the order docs/lerobot.md shows their lines


@pytest.mark.parametrize("kind", KINDS)
def test_bad_input_is_one_line_and_leaves_no_out(v3_export, tmp_path, monkeypatch, refused, kind):
    monkeypatch.chdir(tmp_path)
    shutil.copytree(v3_export, "ds")
    problem = _break(kind, Path("ds"))
    line = refused(["data", "import", "--format", "lerobot", "ds", "out", "--task", "cube-insertion",
                    "--camera-size", SIZE], problem)
    shown = [x for b in doc_blocks("Import") for x in b.splitlines() if x.startswith("wamplan: error: ds")]
    assert len(shown) == len(KINDS) and line == shown[KINDS.index(kind)]  # the doc's line, word for word
    assert not Path("out").exists() and [p.name for p in tmp_path.iterdir() if p.name != "ds"] == []


def test_a_video_shorter_than_its_episode_is_refused(v3_export, tmp_path, refused):
    """A video whose span holds fewer frames than the episode's parquet rows."""
    root = tmp_path / "ds"
    shutil.copytree(v3_export, root)
    path = root / "meta/episodes/chunk-000/file-000.parquet"
    eps = pq.read_table(path).to_pylist()
    eps[1]["videos/observation.images.front/to_timestamp"] -= 2 / 20  # two frames short
    pq.write_table(pa.Table.from_pylist(eps), path)
    refused(["data", "import", "--format", "lerobot", root, tmp_path / "out", "--task", "cube-insertion"],
            "observation.images.front/chunk-000/file-000.mp4: 6 frames for episode 1, but its parquet has 8 rows")
    assert not (tmp_path / "out").exists()


def test_a_sparse_store_is_refused_as_for_cosmos(tmp_path, refused):
    from wamplan.data.store import EpisodeData
    from wamplan.envs.config import EnvConfig

    env = EnvConfig(camera_size=SIZE)
    sparse = EpisodeStore(tmp_path / "sparse", create=True, env=env.task_kwargs(), image_every=4, task=env.spec)
    views = {c: v[[0, 4, 7]] for c, v in _views(0, STEPS, SIZE).items()}
    sparse.write(EpisodeData.logged(env.spec, 0, np.zeros((STEPS, 5)), np.zeros((STEPS + 1, 10)), views, [0, 4, 7]))
    refused(["data", "export", "--format", "lerobot", sparse.root, tmp_path / "out"],
            "stores views every 4 steps, but a LeRobot dataset needs every step's views", "--image-every 1")
    assert not (tmp_path / "out").exists()
