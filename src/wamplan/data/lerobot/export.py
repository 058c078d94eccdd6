"""``wamplan data export --format lerobot STORE OUT``: an episode store as a LeRobotDataset (v3.0, or v2.1).

Per frame (the parquet tables): ``action`` (A,) float32, ``observation.state`` (P,) float32 (the proprio),
``timestamp`` (= frame_index / fps), ``frame_index``, ``episode_index``, ``index`` (over the dataset), ``task_index``;
per camera a video feature ``observation.images.<camera>`` (the task's cameras, in order).

Steps: as for Cosmos Policy's layout (wamplan.data.export), a frame is a control step, so the store must keep every
step's views (collected with ``--image-every 1``; any other store is refused). An episode of T steps has T+1 frames,
the last showing the final state; its action is one padding row, a no-op (no motion, the last gripper command),
which is what the arm does once the episode has ended. The episodes record it (``wamplan/padded_final_action``),
and ``data import --format lerobot`` drops the last frame's action again, so a store survives the round trip.

wamplan's own episode fields ride in the episodes metadata: ``wamplan/seed``, ``wamplan/source``,
``wamplan/success``, ``wamplan/outcome``; ``meta/wamplan.json`` records the store, its task and env settings, the
codec and the package's provenance (LeRobot's readers ignore a file they do not know).

fps: the task's control frequency (ManiSkill's ``control_freq``, 20 Hz for every registered task), or ``--fps``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from wamplan.config import check_numbers, field, require
from wamplan.data.export import episode_arrays, require_every_step
from wamplan.data.lerobot import layout as L
from wamplan.data.lerobot.video import CODECS, VideoWriter, pick_codec, video_info
from wamplan.data.store import EpisodeData, EpisodeStore
from wamplan.envs.spec import TaskSpec
from wamplan.errors import UserError

WAMPLAN_FIELDS = ("wamplan/seed", "wamplan/source", "wamplan/success", "wamplan/outcome", "wamplan/padded_final_action")


@dataclass(frozen=True)
class LeRobotExportConfig:
    """How a store becomes a LeRobotDataset."""

    lerobot_version: str = field("3.0", "LeRobotDataset version to write: 3.0 (episodes as spans of shared files) "
                                        "or 2.1 (a file an episode)", choices=L.WRITES)
    fps: int = field(0, "lerobot: frames per second of the dataset (0: the task's control frequency)")
    vcodec: str = field("auto", "lerobot: video encoder; auto = AV1 (SVT-AV1, LeRobot's default) where PyAV has it, "
                                "else H.264", choices=CODECS)
    crf: int = field(30, "lerobot: the encoder's constant rate factor (lower: larger files, closer frames)")
    image_size: int = field(0, "square size of the exported views; 0 keeps the store's", cli=False)
    instruction: str = field("", "the task string (default: the store's task's instruction)", cli=False)
    sources: tuple[str, ...] = field((), "export only these sources; empty: every episode", cli=False)

    def __post_init__(self) -> None:
        check_numbers(self)
        require(self.lerobot_version in L.WRITES, f"--lerobot-version must be one of {list(L.WRITES)}, got "
                                                  f"'{self.lerobot_version}'")
        require(self.fps >= 0, f"--fps must be >= 0 (0: the task's control frequency), got {self.fps}")
        require(self.vcodec in CODECS, f"--vcodec must be one of {list(CODECS)}, got '{self.vcodec}'")
        require(0 <= self.crf <= 63, f"--crf must lie in 0..63, got {self.crf}")
        require(self.image_size >= 0, f"--image-size must be >= 0 (0 keeps the store's size), got {self.image_size}")
        require(self.instruction == "" or bool(self.instruction.strip()), "--instruction must not be blank")


def task_fps(task: TaskSpec) -> int:
    """The control frequency of ``task``'s ManiSkill env (its ``_default_sim_config``; ManiSkill's default 20 Hz)."""
    import importlib

    from mani_skill.utils.registration import REGISTERED_ENVS

    importlib.import_module(task.adapter.split(":")[0])  # registers the task's env where wamplan defines it
    entry = REGISTERED_ENVS.get(task.env_id)
    if entry is None:
        raise UserError(f"task '{task.name}' runs {task.env_id}, which ManiSkill does not know here, so its control "
                        f"frequency is unknown; pass --fps")
    return int(entry.cls._default_sim_config.fget(None).control_freq)


def _names(task: TaskSpec) -> tuple[list[str], list[str]]:
    action = [("gripper" if i == task.gripper_index else f"a{i}") for i in range(task.action_dim)]
    return action, [f"p{i}" for i in range(task.proprio_dim)]


class _Files:
    """Where each episode's rows and frames go: v3.0 appends episodes to shared files (a new file once one passes
    LeRobot's size limit), v2.1 opens one of each an episode."""

    def __init__(self, root: Path, v3: bool, keys: list[str], fps: int, codec: str, crf: int):
        self.root, self.v3, self.fps, self.codec, self.crf = root, v3, fps, codec, crf
        self.data: dict[str, Any] = dict(chunk=0, file=0, writer=None, path=None)
        self.videos: dict[str, dict[str, Any]] = {k: dict(chunk=0, file=0, writer=None) for k in keys}

    @staticmethod
    def _next(s: dict) -> None:
        s["file"] += 1
        if s["file"] == L.CHUNKS_SIZE:
            s["chunk"], s["file"] = s["chunk"] + 1, 0

    def write_rows(self, ep_index: int, table: pa.Table) -> dict[str, int]:
        d = self.data
        if not self.v3:
            chunk = ep_index // L.CHUNKS_SIZE
            path = self.root / L.DATA_V2.format(episode_chunk=chunk, episode_index=ep_index)
            path.parent.mkdir(parents=True, exist_ok=True)
            pq.write_table(table, path)
            return {}
        if d["writer"] is None:
            d["path"] = self.root / L.DATA_V3.format(chunk_index=d["chunk"], file_index=d["file"])
            d["path"].parent.mkdir(parents=True, exist_ok=True)
            d["writer"] = pq.ParquetWriter(d["path"], table.schema)
        d["writer"].write_table(table)
        where = {"data/chunk_index": d["chunk"], "data/file_index": d["file"]}
        if d["path"].stat().st_size / 2**20 >= L.DATA_FILE_MB:
            self._close_data()
        return where

    def _close_data(self) -> None:
        if self.data["writer"] is not None:
            self.data["writer"].close()
            self.data["writer"] = None
            self._next(self.data)

    def write_frames(self, ep_index: int, key: str, frames: np.ndarray) -> dict[str, Any]:
        h, w = frames.shape[1:3]
        if not self.v3:
            path = self.root / L.VIDEO_V2.format(episode_chunk=ep_index // L.CHUNKS_SIZE, video_key=key,
                                                 episode_index=ep_index)
            v = VideoWriter(path, self.fps, w, h, self.codec, self.crf)
            v.add(frames)
            v.close()
            return {}
        s = self.videos[key]
        if s["writer"] is None:
            path = self.root / L.VIDEO_V3.format(video_key=key, chunk_index=s["chunk"], file_index=s["file"])
            s["writer"] = VideoWriter(path, self.fps, w, h, self.codec, self.crf)
        v = s["writer"]
        start = v.frames
        v.add(frames)
        where = {f"videos/{key}/chunk_index": s["chunk"], f"videos/{key}/file_index": s["file"],
                 f"videos/{key}/from_timestamp": start / self.fps, f"videos/{key}/to_timestamp": v.frames / self.fps}
        if v.size_mb() >= L.VIDEO_FILE_MB:
            v.close()
            s["writer"] = None
            self._next(s)
        return where

    def close(self) -> None:
        self._close_data()
        for s in self.videos.values():
            if s["writer"] is not None:
                s["writer"].close()
                s["writer"] = None


def export_lerobot(store_dir: str | Path, out_dir: str | Path, cfg: LeRobotExportConfig = LeRobotExportConfig(),
                   log=None) -> dict[str, Any]:
    """Write ``store_dir``'s episodes as a LeRobotDataset at ``out_dir`` (see the module docstring); ``out_dir``
    appears whole when done, or not at all. Returns a summary (episodes, frames, codec, seconds, frames/s)."""
    t0 = time.perf_counter()
    store = EpisodeStore(store_dir)
    task = store.task
    require_every_step(store, "a LeRobot dataset")
    metas = [m for m in store.iter_meta() if not cfg.sources or m["source"] in cfg.sources]
    if not metas:
        raise UserError(f"{store_dir} has no episode to export (sources {list(cfg.sources) or 'all'}); check "
                        f"--sources or the store")
    fps = cfg.fps or task_fps(task)
    codec = pick_codec(cfg.vcodec)
    v3 = cfg.lerobot_version == "3.0"
    keys = [L.camera_key(c) for c in store.cameras]
    instruction = cfg.instruction or task.instruction
    action_names, state_names = _names(task)
    with L.whole_or_nothing(Path(out_dir)) as root:
        files = _Files(root, v3, keys, fps, codec, cfg.crf)
        episodes, per_stats, total, size = [], [], 0, None
        try:
            for e, meta in enumerate(metas):
                ep = store.load(meta["path"])
                arr = episode_arrays(ep, cfg.image_size, task, "a LeRobot dataset")
                n = int(arr["actions"].shape[0])  # T + 1 frames
                table = _frame_table(arr["actions"], arr["proprio"], e, total, fps)
                row: dict[str, Any] = {"episode_index": e, "tasks": [instruction], "length": n}
                row.update(files.write_rows(e, table))
                if v3:
                    row.update({"dataset_from_index": total, "dataset_to_index": total + n})
                for cam, key in zip(store.cameras, keys):
                    row.update(files.write_frames(e, key, arr["images"][cam]))
                size = size or arr["images"][store.cameras[0]].shape[1:3]
                stats = {L.ACTION: L.vector_stats(arr["actions"]), L.STATE: L.vector_stats(arr["proprio"]),
                         **{k: L.vector_stats(table.column(k).to_numpy().reshape(-1, 1)) for k in L.INDEX_COLUMNS},
                         **{key: L.image_stats(arr["images"][cam]) for cam, key in zip(store.cameras, keys)}}
                row.update(_wamplan_fields(ep))
                episodes.append((row, stats))
                per_stats.append(stats)
                total += n
        finally:
            files.close()
        features = {L.ACTION: L.vector_feature(task.action_dim, action_names),
                    L.STATE: L.vector_feature(task.proprio_dim, state_names),
                    **{k: dict(dtype="video", shape=[int(size[0]), int(size[1]), 3], names=["height", "width", "channels"])
                       for k in keys},
                    **L.index_features(fps if v3 else None)}
        first = {k: (root / (L.VIDEO_V3.format(video_key=k, chunk_index=0, file_index=0) if v3 else
                             L.VIDEO_V2.format(episode_chunk=0, video_key=k, episode_index=0))) for k in keys}
        for k in keys:
            features[k]["info"] = video_info(first[k])
        if v3:
            features[L.ACTION]["fps"] = features[L.STATE]["fps"] = fps
        total_stats = {k: L.aggregate_stats([s[k] for s in per_stats]) for k in per_stats[0]}
        _write_meta(root, v3, episodes, features, fps, total, instruction, task, keys)
        L.write_json(root / L.STATS, L.stats_json(total_stats))
        L.write_json(root / L.WAMPLAN, dict(store=str(Path(store_dir).resolve()), task=task.describe(), env=store.env,
                                            cameras=list(store.cameras), image_size=cfg.image_size or None,
                                            codec=codec, crf=cfg.crf, padded_final_action=True,
                                            provenance=store.manifest.get("provenance", {})))
    seconds = time.perf_counter() - t0
    return dict(out=str(out_dir), version=f"v{cfg.lerobot_version}", episodes=len(episodes), frames=total, fps=fps,
                cameras=keys, codec=codec, seconds=round(seconds, 2), frames_per_second=round(total / seconds, 1))


def _frame_table(actions: np.ndarray, proprio: np.ndarray, episode: int, start: int, fps: int) -> pa.Table:
    n = len(actions)
    frame = np.arange(n, dtype=np.int64)
    return pa.table({L.ACTION: L.vector_column(actions), L.STATE: L.vector_column(proprio),
                     "timestamp": pa.array((frame / fps).astype(np.float32)), "frame_index": pa.array(frame),
                     "episode_index": pa.array(np.full(n, episode, np.int64)),
                     "index": pa.array(start + frame), "task_index": pa.array(np.zeros(n, np.int64))})


def _wamplan_fields(ep: EpisodeData) -> dict[str, Any]:
    return dict(zip(WAMPLAN_FIELDS, (int(ep.seed), ep.source, bool(ep.success), ep.outcome, True)))


def _write_meta(root: Path, v3: bool, episodes: list[tuple[dict, dict]], features: dict, fps: int, total: int,
                instruction: str, task: TaskSpec, keys: list[str]) -> None:
    n = len(episodes)
    info: dict[str, Any] = {"codebase_version": "v3.0" if v3 else "v2.1", "robot_type": task.name,
                            "total_episodes": n, "total_frames": total, "total_tasks": 1}
    if v3:
        info.update(chunks_size=L.CHUNKS_SIZE, data_files_size_in_mb=L.DATA_FILE_MB,
                    video_files_size_in_mb=L.VIDEO_FILE_MB)
    else:
        info.update(total_chunks=(n - 1) // L.CHUNKS_SIZE + 1, total_videos=n * len(keys), chunks_size=L.CHUNKS_SIZE)
    info.update(fps=fps, splits={"train": f"0:{n}"}, data_path=L.DATA_V3 if v3 else L.DATA_V2,
                video_path=L.VIDEO_V3 if v3 else L.VIDEO_V2, features=features)
    L.write_json(root / L.INFO, info)
    if not v3:
        L.write_jsonl(root / L.TASKS_JSONL, [{"task_index": 0, "task": instruction}])
        L.write_jsonl(root / L.EPISODES_JSONL, [row for row, _ in episodes])
        L.write_jsonl(root / L.EPISODES_STATS_JSONL, [{"episode_index": row["episode_index"],
                                                        "stats": L.stats_json(stats)} for row, stats in episodes])
        return
    pq.write_table(pa.table({"task_index": pa.array([0], pa.int64()), "__index_level_0__": [instruction]},
                            metadata={b"pandas": json.dumps(_PANDAS_TASKS).encode()}), _mk(root / L.TASKS))
    rows = []
    for row, stats in episodes:
        row = dict(row, **{"meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0})
        row.update({f"stats/{k}/{name}": np.asarray(v).tolist() for k, s in stats.items() for name, v in s.items()})
        rows.append(row)
    pq.write_table(pa.Table.from_pylist(rows), _mk(root / L.EPISODES_FILE.format(chunk_index=0, file_index=0)))


def _mk(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


# LeRobot writes tasks.parquet from a pandas DataFrame indexed by the task string; this metadata lets pandas (and so
# LeRobot's reader) restore that index
_PANDAS_TASKS = {"index_columns": ["__index_level_0__"], "column_indexes": [{"name": None, "field_name": None,
                 "pandas_type": "unicode", "numpy_type": "object", "metadata": {"encoding": "UTF-8"}}],
                 "columns": [{"name": "task_index", "field_name": "task_index", "pandas_type": "int64",
                              "numpy_type": "int64", "metadata": None},
                             {"name": None, "field_name": "__index_level_0__", "pandas_type": "unicode",
                              "numpy_type": "object", "metadata": None}],
                 "creator": {"library": "pyarrow", "version": pa.__version__}, "pandas_version": "2.2.0"}
