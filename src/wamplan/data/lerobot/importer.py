"""``wamplan data import --format lerobot DIR OUT --task NAME``: a LeRobotDataset (v3.0, v2.1 or v2.0) as a wamplan
episode store of a registered task, what ``wm train`` and ``wam train`` read.

Keys: the task's actions come from ``action``, its proprio from ``observation.state``, camera ``c``'s views from
``observation.images.c`` (what ``data export --format lerobot`` writes). A dataset named otherwise is read through
a key map, ``OURS=THEIRS`` a pair: openpi's LIBERO set (``image``, ``wrist_image``, ``state``, ``actions``) into a
task with cameras ``agentview`` and ``wrist`` takes ``observation.images.agentview=image
observation.images.wrist=wrist_image observation.state=state action=actions``. A view is a video feature (decoded
from its MP4 span) or an image feature (PNG or JPEG bytes in the parquet, as LeRobot writes images); each is resized
to the store's square camera size.

Steps: N frames make an episode of T = N-1 steps: the images and proprio of every frame, the actions of all frames
but the last (whose action leads to no recorded frame; in wamplan's own exports it is the padding row), views at
every step (``image_every`` 1) or every ``image_every``-th step and the last. wamplan's episode fields
(``wamplan/seed``, ``source``, ``success``, ``outcome``) are restored where the dataset has them; otherwise the
episode's seed is its ``episode_index``, its source ``lerobot`` and its outcome ``logged``.

What such a store cannot feed: it has no simulator state, stage flags or privileged poses, and its seeds are not
env seeds: evaluation (which resets the simulator from a seed), the simulator-oracle dynamics, counterfactual
branches and ``data alignment`` need a collected store; the world model and TinyWAM train on it.
"""

from __future__ import annotations

import io
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from wamplan.config import field, require
from wamplan.data.export import resize_frames
from wamplan.data.lerobot import layout as L
from wamplan.data.lerobot.video import read_span
from wamplan.data.store import EpisodeData, EpisodeStore
from wamplan.envs.config import EnvConfig
from wamplan.errors import reason
from wamplan.provenance import provenance

SOURCE = "lerobot"
REPORT = "import.json"


@dataclass(frozen=True)
class LeRobotImportConfig:
    """How a LeRobot dataset becomes an episode store."""

    key_map: tuple[str, ...] = field((), "OURS=THEIRS pairs for datasets whose keys are not LeRobot's usual ones: "
                                         "action=..., observation.state=..., observation.images.<camera>=...")
    image_every: int = field(1, "keep every N-th frame's views (and the last); 1 keeps all")
    source: str = field(SOURCE, "the episodes' source where the dataset records none of wamplan's")
    episodes: int = field(0, "import only the first N episodes (0: all)")

    def __post_init__(self) -> None:
        for pair in self.key_map:
            ours, _, theirs = pair.partition("=")
            require(bool(ours) and bool(theirs), f"--key-map {pair!r}: write OURS=THEIRS, e.g. action=actions")
        require(self.image_every >= 1, f"--image-every must be >= 1, got {self.image_every}")
        require(bool(self.source.strip()), "--source must not be blank")
        require(self.episodes >= 0, f"--episodes must be >= 0 (0: all), got {self.episodes}")

    def keys(self) -> dict[str, str]:
        return dict(p.split("=", 1) for p in self.key_map)


@dataclass(frozen=True)
class _Episode:
    index: int
    length: int
    fields: dict[str, Any]  # the episodes metadata row (v3.0 parquet, v2.x JSON line)


class _Dataset:
    """The episodes of a LeRobot dataset and, per episode, its table rows and its views."""

    def __init__(self, root: Path):
        self.root, self.info = root, L.read_info(root)
        self.version, self.fps, self.features = self.info["codebase_version"], float(self.info["fps"]), self.info["features"]
        self.v3 = self.version == "v3.0"
        self.chunks = int(self.info.get("chunks_size") or L.CHUNKS_SIZE)
        self.episodes = self._episodes()
        self._tables: dict[Path, pa.Table] = {}

    def _episodes(self) -> list[_Episode]:
        if self.v3:
            files = sorted((self.root / "meta/episodes").glob("*/*.parquet"))
            if not files:
                raise L.LeRobotError(f"{self.root / 'meta/episodes'} holds no parquet file; a v3.0 dataset lists its "
                                     f"episodes there (the dataset is incomplete)")
            rows = [r for f in files for r in L.read_table(f, "episodes metadata").to_pylist()]
            where = self.root / "meta/episodes"
        else:
            rows = L.read_jsonl(self.root / L.EPISODES_JSONL, "episodes metadata")
            where = self.root / L.EPISODES_JSONL
        eps = []
        for r in rows:
            if not isinstance(r.get("episode_index"), int) or not isinstance(r.get("length"), int):
                raise L.LeRobotError(f"{where}: an episode lacks its episode_index or length; the dataset is damaged")
            eps.append(_Episode(r["episode_index"], r["length"], r))
        return sorted(eps, key=lambda e: e.index)

    def _table(self, path: Path) -> pa.Table:
        if path not in self._tables:
            self._tables = {path: L.read_table(path, "frame data")}  # episodes come in file order: keep one
        return self._tables[path]

    def rows(self, ep: _Episode) -> tuple[pa.Table, Path]:
        """The episode's frames (rows sorted by frame_index) and the file they are in; one line if their number is
        not the episode's length."""
        if self.v3:
            f = ep.fields
            path = self.root / self.info.get("data_path", L.DATA_V3).format(
                chunk_index=f.get("data/chunk_index", 0), file_index=f.get("data/file_index", 0))
        else:
            path = self.root / self.info.get("data_path", L.DATA_V2).format(
                episode_chunk=ep.index // self.chunks, episode_index=ep.index)
        table = self._table(path)
        if "episode_index" in table.column_names:
            table = table.filter(pc.equal(table.column("episode_index"), ep.index))
        if "frame_index" in table.column_names:
            table = table.sort_by("frame_index")
        if table.num_rows != ep.length:
            raise L.LeRobotError(f"{path}: episode {ep.index} has {table.num_rows} rows, but the episodes metadata "
                                 f"gives it {ep.length} frames; the dataset is damaged")
        return table, path

    def views(self, ep: _Episode, key: str, table: pa.Table, data_path: Path) -> np.ndarray:
        """(N, H, W, 3) uint8 views of ``key`` for the episode's N frames; one line if their number differs."""
        if self.features[key]["dtype"] == "video":
            if self.v3:
                f = ep.fields
                path = self.root / self.info["video_path"].format(
                    video_key=key, chunk_index=f.get(f"videos/{key}/chunk_index", 0),
                    file_index=f.get(f"videos/{key}/file_index", 0))
                start, end = f.get(f"videos/{key}/from_timestamp", 0.0), f.get(f"videos/{key}/to_timestamp")
            else:
                path = self.root / self.info["video_path"].format(episode_chunk=ep.index // self.chunks,
                                                                  video_key=key, episode_index=ep.index)
                start, end = 0.0, None
            frames = read_span(path, float(start), None if end is None else float(end), self.fps,
                               f"{key} of episode {ep.index}")
            if len(frames) != ep.length:
                raise L.LeRobotError(f"{path}: {len(frames)} frames for episode {ep.index}, but its parquet has "
                                     f"{ep.length} rows; the dataset is damaged")
            return frames
        return self._images(table.column(key), key, data_path)

    def _images(self, col: pa.ChunkedArray, key: str, where: Path) -> np.ndarray:
        from PIL import Image, UnidentifiedImageError

        out = []
        for i, cell in enumerate(col.to_pylist()):
            try:
                if isinstance(cell, dict) and cell.get("bytes"):
                    img = Image.open(io.BytesIO(cell["bytes"]))
                elif isinstance(cell, dict) and cell.get("path"):
                    img = Image.open(self.root / cell["path"])
                else:
                    img = Image.fromarray(np.asarray(cell, np.uint8))  # (H, W, 3) nested lists
                out.append(np.asarray(img.convert("RGB")))  # (H, W, 3)
            except (OSError, UnidentifiedImageError, ValueError, TypeError) as e:
                raise L.LeRobotError(f"{where}: {key} of row {i} is not an image ({reason(e)}); the dataset is "
                                     f"damaged") from None
        return np.stack(out)  # (N, H, W, 3)


def _resolve_keys(ds: _Dataset, task, cfg: LeRobotImportConfig) -> dict[str, str]:
    """OURS -> the dataset's key, for the action, the state and every camera; one line naming what is missing."""
    wanted = [L.ACTION, L.STATE, *(L.camera_key(c) for c in task.cameras)]
    given = cfg.keys()
    if unknown := sorted(set(given) - set(wanted)):
        raise L.LeRobotError(f"--key-map {unknown[0]}=...: task '{task.name}' reads only {', '.join(wanted)}")
    keys = {ours: given.get(ours, ours) for ours in wanted}
    info = ds.root / L.INFO
    for ours, theirs in keys.items():
        ft = ds.features.get(theirs)
        if ft is None:
            have = ", ".join(k for k in ds.features if k not in L.INDEX_FEATURES)
            raise L.LeRobotError(f"{info}: no feature '{theirs}' for {ours} (it has {have}); map it with "
                                 f"--key-map {ours}=KEY")
        is_view = ours.startswith(L.IMAGES)
        if is_view and ft["dtype"] not in ("video", "image"):
            raise L.LeRobotError(f"{info}: '{theirs}' is {ft['dtype']}, not an image or video feature, so not {ours}")
        want = task.action_dim if ours == L.ACTION else task.proprio_dim
        if not is_view and list(ft["shape"]) != [want]:
            raise L.LeRobotError(f"{info}: '{theirs}' has shape {ft['shape']}, but task '{task.name}' has {want}-D "
                                 f"{'actions' if ours == L.ACTION else 'proprio'}; import into a task of the same "
                                 f"sizes (register one: docs/lerobot.md)")
    return keys


def _episode_fields(ep: _Episode, cfg: LeRobotImportConfig) -> dict[str, Any]:
    f = ep.fields
    if "wamplan/seed" in f:
        return dict(seed=int(f["wamplan/seed"]), source=str(f["wamplan/source"]), success=bool(f["wamplan/success"]),
                    outcome=str(f["wamplan/outcome"]))
    return dict(seed=ep.index, source=cfg.source, success=False, outcome="logged")


def _read(ds: _Dataset, task, keys: dict[str, str], size: int, cfg: LeRobotImportConfig) -> Iterator[EpisodeData]:
    chosen = ds.episodes[:cfg.episodes] if cfg.episodes else ds.episodes
    for ep in chosen:
        table, path = ds.rows(ep)
        if ep.length < 2:
            raise L.LeRobotError(f"{path}: episode {ep.index} has {ep.length} frame(s); an episode needs two or more "
                                 f"(a step between frames)")
        actions = L.column_array(table, keys[L.ACTION], path)  # (N, A)
        proprio = L.column_array(table, keys[L.STATE], path)  # (N, P)
        T = ep.length - 1
        steps = list(range(0, T + 1, cfg.image_every)) + ([T] if T % cfg.image_every else [])
        images = {c: resize_frames(ds.views(ep, keys[L.camera_key(c)], table, path)[steps], size) for c in task.cameras}
        yield EpisodeData.logged(task, actions=actions[:T], proprio=proprio, images=images, image_steps=steps,
                                 image_every=cfg.image_every, **_episode_fields(ep, cfg),
                                 provenance=dict(lerobot=str(ds.root.resolve()), version=ds.version,
                                                 episode_index=ep.index, fps=ds.fps, keys=keys))


def import_lerobot(dataset: str | Path, out: str | Path, env: EnvConfig,
                   cfg: LeRobotImportConfig = LeRobotImportConfig()) -> dict[str, Any]:
    """Write the LeRobot dataset ``dataset`` as an episode store at ``out`` for ``env.task`` (views resized to
    ``env.camera_size``); ``out`` appears whole when done, or not at all. Returns the summary also written to
    ``out/import.json``."""
    t0 = time.perf_counter()
    ds = _Dataset(Path(dataset))
    task = env.spec
    keys = _resolve_keys(ds, task, cfg)
    frames = 0
    with L.whole_or_nothing(Path(out)) as root:
        store = EpisodeStore(root, create=True, env=env.task_kwargs(), image_every=cfg.image_every,
                             provenance=dict(provenance(), imported_from=str(Path(dataset).resolve())), task=task)
        n, seen = 0, {}
        for ep in _read(ds, task, keys, env.camera_size, cfg):
            index = ep.provenance["episode_index"]
            if (other := seen.setdefault((ep.source, ep.seed), index)) != index:
                raise L.LeRobotError(f"{ds.root}: episodes {other} and {index} are both source '{ep.source}' seed "
                                     f"{ep.seed} (wamplan/seed), and a store holds one episode a seed; the dataset "
                                     f"was merged from stores that share seeds")
            store.write(ep)
            n += 1
            frames += ep.length + 1
        seconds = time.perf_counter() - t0
        report = dict(dataset=str(dataset), version=ds.version, fps=ds.fps, task=task.name, keys=keys,
                      camera_size=env.camera_size, image_every=cfg.image_every, episodes=n, frames=frames,
                      seconds=round(seconds, 2), frames_per_second=round(frames / seconds, 1))
        L.write_json(root / REPORT, report)
    return dict(report, out=str(out))
