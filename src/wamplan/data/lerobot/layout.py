"""What export and import share: the versions and their paths, ``meta/info.json``, parquet columns, stats, and the
output directory that appears whole or not at all."""

from __future__ import annotations

import json
import os
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from wamplan.errors import UserError, reason

READS = ("v2.0", "v2.1", "v3.0")  # codebase versions the importer reads (v2.0: v2.1's files without episode stats)
WRITES = ("2.1", "3.0")  # versions the exporter writes (--lerobot-version)

INFO = "meta/info.json"
STATS = "meta/stats.json"
WAMPLAN = "meta/wamplan.json"  # our provenance; LeRobot's readers ignore files they do not know
# v3.0
TASKS = "meta/tasks.parquet"
EPISODES_FILE = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
DATA_V3 = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_V3 = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
# v2.x
EPISODES_JSONL, TASKS_JSONL, EPISODES_STATS_JSONL = "meta/episodes.jsonl", "meta/tasks.jsonl", "meta/episodes_stats.jsonl"
DATA_V2 = "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"
VIDEO_V2 = "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4"

CHUNKS_SIZE = 1000  # files a chunk directory holds (LeRobot's default)
DATA_FILE_MB, VIDEO_FILE_MB = 100, 200  # v3.0: a shared file is closed after the episode that takes it past this

ACTION, STATE, IMAGES = "action", "observation.state", "observation.images."  # LeRobot's key names
INDEX_COLUMNS = ("timestamp", "frame_index", "episode_index", "index", "task_index")
INDEX_FEATURES = {"timestamp": "float32", "frame_index": "int64", "episode_index": "int64", "index": "int64",
                  "task_index": "int64"}
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)  # the per-feature quantiles LeRobot's stats carry (q01 .. q99)
STAT_NAMES = ("min", "max", "mean", "std", "count", *(f"q{round(q * 100):02d}" for q in QUANTILES))


class LeRobotError(UserError):
    """A directory is not a LeRobot dataset wamplan can read, or a part of it disagrees with another; the message
    names the file and what is wrong."""


def camera_key(camera: str) -> str:
    return IMAGES + camera


# ---------------------------------------------------------------------------------------------------- info.json
def read_info(root: Path) -> dict[str, Any]:
    """``root/meta/info.json`` of a LeRobot dataset of a version in :data:`READS`, checked for what the importer
    needs (fps, features with dtype and shape); one :class:`LeRobotError` naming the file otherwise."""
    if not root.is_dir():
        raise LeRobotError(f"{root} {'does not exist' if not root.exists() else 'is a file'}; pass a LeRobot "
                           f"dataset directory (the one holding meta/info.json)")
    path = root / INFO
    if not path.is_file():
        raise LeRobotError(f"{root} is not a LeRobot dataset: {INFO} is missing (pass the directory holding meta/ "
                           f"and data/)")
    try:
        info = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise LeRobotError(f"{path} cannot be read as JSON ({reason(e)}); the dataset is damaged") from None
    if not isinstance(info, dict):
        raise LeRobotError(f"{path} is not a LeRobot info.json (a JSON object); the dataset is damaged")
    version = info.get("codebase_version")
    if version not in READS:
        raise LeRobotError(f"{path}: codebase_version {version!r} is not a LeRobot version this reader knows "
                           f"({', '.join(READS)}); convert it with LeRobot's own tools")
    fps, features = info.get("fps"), info.get("features")
    if not isinstance(fps, (int, float)) or isinstance(fps, bool) or not fps > 0:
        raise LeRobotError(f"{path}: fps is {fps!r}, not a positive number; the dataset is damaged")
    if not isinstance(features, dict) or not all(isinstance(f, dict) and "dtype" in f and isinstance(f.get("shape"), list)
                                                 for f in features.values()):
        raise LeRobotError(f"{path}: 'features' must map each key to its dtype and shape; the dataset is damaged")
    return info


def vector_feature(dim: int, names: Sequence[str] | None = None) -> dict[str, Any]:
    return dict(dtype="float32", shape=[dim], names=list(names) if names else None)


def index_features(fps: int | None = None) -> dict[str, dict[str, Any]]:
    """The five bookkeeping columns every frame has (v3.0 writes each non-video feature's fps too)."""
    return {k: dict(dtype=t, shape=[1], names=None, **({"fps": fps} if fps else {})) for k, t in INDEX_FEATURES.items()}


# ---------------------------------------------------------------------------------------------------- parquet
def vector_column(values: np.ndarray) -> pa.Array:
    """(N, D) -> a fixed-size list column of D float32 (LeRobot's ``Sequence(length=D)``)."""
    values = np.ascontiguousarray(values, np.float32)  # (N, D)
    return pa.FixedSizeListArray.from_arrays(pa.array(values.reshape(-1)), values.shape[1])


def column_array(table: pa.Table, key: str, where: Path) -> np.ndarray:
    """The numeric column ``key`` of ``table`` as (N, D) float32 (scalars as (N, 1)); one line if it is neither."""
    col = table.column(key).combine_chunks()
    try:
        if pa.types.is_fixed_size_list(col.type) or pa.types.is_list(col.type) or pa.types.is_large_list(col.type):
            n = len(col)
            flat = col.flatten().to_numpy(zero_copy_only=False).astype(np.float32)
            return flat.reshape(n, -1) if n else np.zeros((0, 0), np.float32)  # (N, D)
        return col.to_numpy(zero_copy_only=False).astype(np.float32).reshape(-1, 1)  # (N, 1)
    except (pa.ArrowException, ValueError, TypeError) as e:
        raise LeRobotError(f"{where}: column '{key}' is not a numeric vector per frame ({reason(e)})") from None


def read_table(path: Path, what: str, columns: Sequence[str] | None = None) -> pa.Table:
    """A parquet file of the dataset; one line naming it when it is missing or not parquet."""
    if not path.is_file():
        raise LeRobotError(f"{path} is missing ({what}); the dataset is incomplete")
    try:
        return pq.read_table(path, columns=list(columns) if columns else None)
    except (pa.ArrowException, OSError, KeyError) as e:
        raise LeRobotError(f"{path} cannot be read as parquet ({what}: {reason(e)}); the dataset is damaged") from None


def read_jsonl(path: Path, what: str) -> list[dict[str, Any]]:
    if not path.is_file():
        raise LeRobotError(f"{path} is missing ({what}); the dataset is incomplete")
    try:
        return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]
    except (OSError, ValueError) as e:
        raise LeRobotError(f"{path} is not JSON lines ({what}: {reason(e)}); the dataset is damaged") from None


def write_jsonl(path: Path, rows: Sequence[dict[str, Any]]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(json.dumps(r) + "\n" for r in rows), encoding="utf-8")


def write_json(path: Path, obj: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=4) + "\n", encoding="utf-8")


# ---------------------------------------------------------------------------------------------------- stats
def vector_stats(x: np.ndarray) -> dict[str, np.ndarray]:
    """Per-entry stats of (N, D) values: min, max, mean, std, count, q01..q99 (each (D,), count (1,))."""
    x = np.asarray(x, np.float64)  # (N, D)
    qs = np.quantile(x, QUANTILES, axis=0)  # (Q, D)
    return dict(min=x.min(0), max=x.max(0), mean=x.mean(0), std=x.std(0), count=np.array([len(x)]),
                **{f"q{round(q * 100):02d}": qs[i] for i, q in enumerate(QUANTILES)})


def image_stats(frames: np.ndarray, max_frames: int = 100, max_side: int = 64) -> dict[str, np.ndarray]:
    """Per-channel stats of (N, H, W, 3) uint8 frames in [0, 1], each (3, 1, 1) as LeRobot's; like LeRobot's they
    are estimated on a sample (at most ``max_frames`` frames, every k-th pixel down to about ``max_side``)."""
    idx = np.unique(np.linspace(0, len(frames) - 1, min(max_frames, len(frames))).round().astype(int))
    step = max(1, max(frames.shape[1:3]) // max_side)
    x = frames[idx, ::step, ::step].reshape(-1, 3).astype(np.float64) / 255.0  # (n pixels, 3)
    s = vector_stats(x)
    return {k: (v if k == "count" else v.reshape(3, 1, 1)) for k, v in dict(s, count=np.array([len(frames)])).items()}


def aggregate_stats(episodes: Sequence[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """One feature's stats over episodes: exact min, max, mean, std and count; quantiles as the count-weighted mean
    of the episodes' (as LeRobot aggregates them)."""
    n = np.array([float(e["count"][0]) for e in episodes])  # (E,)
    w = (n / n.sum()).reshape(-1, *([1] * np.ndim(episodes[0]["mean"])))  # (E, 1...)
    means = np.stack([e["mean"] for e in episodes])  # (E, ...)
    mean = (w * means).sum(0)
    var = (w * (np.stack([e["std"] for e in episodes]) ** 2 + (means - mean) ** 2)).sum(0)
    out = dict(min=np.min([e["min"] for e in episodes], 0), max=np.max([e["max"] for e in episodes], 0), mean=mean,
               std=np.sqrt(var), count=np.array([int(n.sum())]))
    out.update({k: (w * np.stack([e[k] for e in episodes])).sum(0) for k in STAT_NAMES if k.startswith("q")})
    return out


def stats_json(stats: dict[str, dict[str, np.ndarray]]) -> dict[str, dict[str, list]]:
    return {key: {name: np.asarray(v).tolist() for name, v in s.items()} for key, s in stats.items()}


# ---------------------------------------------------------------------------------------------------- output
@contextmanager
def whole_or_nothing(out: Path) -> Iterator[Path]:
    """A temporary directory beside ``out`` to write into, renamed to ``out`` when the ``with`` body ends well and
    removed when it fails (or is interrupted): ``out`` is complete or absent."""
    from wamplan.data.export import require_empty

    out = Path(out)
    require_empty(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.part-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        yield tmp
        if out.is_dir():
            out.rmdir()  # empty (checked above): the rename replaces it
        os.replace(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
