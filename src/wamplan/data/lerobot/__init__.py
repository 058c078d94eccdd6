"""LeRobot datasets in and out: ``wamplan data export --format lerobot`` and ``wamplan data import --format lerobot``.

The LeRobotDataset is the layout openpi, GR00T and lerobot train on: parquet tables (one row a frame) beside one
video a camera, described by ``meta/info.json``. Two versions are in use:

- v3.0 (lerobot >= 0.4): episodes are spans of shared files, ``data/chunk-000/file-000.parquet`` and
  ``videos/<key>/chunk-000/file-000.mp4``; ``meta/episodes/chunk-000/file-000.parquet`` holds one row an episode
  (its rows ``dataset_from_index .. dataset_to_index`` of the data, its span ``from_timestamp .. to_timestamp`` of
  each video, its stats), ``meta/tasks.parquet`` the task strings.
- v2.1 (and v2.0, its predecessor with the same files but no per-episode stats): one parquet file and one video a
  camera per episode, ``data/chunk-000/episode_000000.parquet``, ``videos/chunk-000/<key>/episode_000000.mp4``; the
  metadata in JSON lines (``meta/episodes.jsonl``, ``meta/tasks.jsonl``, ``meta/episodes_stats.jsonl``).

Only pyarrow and PyAV are needed: ``lerobot`` itself is not a dependency (scripts/check_lerobot_export.sh loads an
export with its reader, in a virtual environment of its own). ``layout`` holds what both directions share (the
versions, paths, ``info.json``, stats, the all-or-nothing output directory), ``video`` the encoding and decoding.
"""

from wamplan.data.lerobot.layout import LeRobotError

__all__ = ["LeRobotError"]
