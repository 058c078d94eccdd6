"""Two conditions of one evaluation on the same seed, one above the other in one video (``wamplan film``):
``RUN/videos/pairs/seed{seed:04d}_c{a}_vs_c{b}.webm``.

By default the seeds are those one condition solved and the other did not. An episode whose video the run did not
film (``--videos`` chose other seeds) is re-run here with the run's stored settings (``eval_config.json``,
:func:`~wamplan.evaluation.runner.config_from_settings`), filmed as ``wamplan eval`` films, and its outcome and
length are checked against its record: re-runs are bit-identical on the machine that made the run, and may differ
elsewhere, which :class:`PairFilmed` says. The two episodes play at their real times; the shorter one's last picture
stays while the other goes on.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from wamplan.evaluation.videos import (DEFAULT_VARIANT, FPS, PAIRS, VIDEOS, VideoConfig, pair_name, variant_of,
                                       video_name)


@dataclass
class PairFilmed:
    """One seed's pair video and what it took: the episodes re-run, and those whose re-run differed from the
    record (condition -> (recorded outcome, length), (re-run outcome, length))."""

    seed: int
    path: Path
    outcomes: dict[int, str]
    rerun: list[int] = field(default_factory=list)
    differed: dict[int, tuple[tuple[str, int], tuple[str, int]]] = field(default_factory=dict)


def paired_records(records: list[dict[str, Any]], a: int, b: int, variant: str = DEFAULT_VARIANT
                   ) -> dict[int, dict[int, dict[str, Any]]]:
    """seed -> {a: record, b: record} for the seeds both conditions ran (of ``variant``)."""
    by: dict[int, dict[int, dict[str, Any]]] = {}
    for r in records:
        if r["condition"] in (a, b) and variant_of(r) == variant:
            by.setdefault(r["seed"], {})[r["condition"]] = r
    return {s: v for s, v in sorted(by.items()) if len(v) == 2}


def disagreeing_seeds(records: list[dict[str, Any]], a: int, b: int, variant: str = DEFAULT_VARIANT) -> list[int]:
    """The seeds one of conditions ``a`` and ``b`` solved and the other did not, in order."""
    pairs = paired_records(records, a, b, variant)
    return [s for s, r in pairs.items() if bool(r[a]["success"]) != bool(r[b]["success"])]


def film_pairs(run: str | Path, a: int, b: int, seeds: list[int], videos: VideoConfig, variant: str = DEFAULT_VARIANT,
               device: str = "auto") -> Iterator[PairFilmed]:
    """Write the pair video of each of ``seeds`` (each must have records of both conditions), re-running and
    filming the episodes ``run/videos`` lacks; yields what each took."""
    from wamplan.evaluation.records import read_records
    from wamplan.evaluation.runner import VIDEO_KEY, EvalWorker, config_from_settings
    from wamplan.evaluation.videos import write_episode_videos

    run = Path(run)
    pairs = paired_records(read_records(run), a, b, variant)
    worker = None
    for seed in seeds:
        found: dict[int, Path] = {}
        filmed = PairFilmed(seed, run / VIDEOS / PAIRS / pair_name(seed, a, b), {})
        for c in (a, b):
            rec = pairs[seed][c]
            path = run / VIDEOS / video_name(c, seed, bool(rec["success"]), variant)
            if not path.is_file():
                if worker is None:  # built once, for the first episode to re-run
                    worker = EvalWorker(config_from_settings(run, variant, device), videos, frozenset(seeds))
                again = worker((c, seed))
                write_episode_videos(run, c, seed, variant, bool(again["success"]), again.pop(VIDEO_KEY, {}))
                filmed.rerun.append(c)
                was, now = (rec["outcome"], rec["length"]), (again["outcome"], again["length"])
                if was != now:
                    filmed.differed[c] = (was, now)
                rec = again
                path = run / VIDEOS / video_name(c, seed, bool(rec["success"]), variant)
            found[c] = path
            filmed.outcomes[c] = f"{rec['outcome']}, {rec['length']} steps"
        write_pair(filmed.path, [(f"condition {c}: {filmed.outcomes[c]}", found[c]) for c in (a, b)])
        yield filmed


def write_pair(path: Path, rows: list[tuple[str, Path]]) -> None:
    """One WebM of the videos ``rows`` (label, path) one above the other, each captioned, on one timeline: at every
    time any of them shows a new picture, each shows its latest (its last once it has ended)."""
    from wamplan.envs.media import caption, encode_webm, read_video

    clips = [read_video(p, FPS) for _, p in rows]  # (pictures, steps) each
    times = sorted({t for _, steps in clips for t in steps})
    width = clips[0][0][0].shape[1]
    pictures = []
    for t in times:
        parts = []
        for (label, _), (pics, steps) in zip(rows, clips):
            i = max(0, int(np.searchsorted(steps, t, side="right")) - 1)  # its latest picture at t
            pic = pics[i]
            if pic.shape[1] != width:  # a video filmed at another --video-size
                pic = _fit_width(pic, width)
            parts.append(caption(pic, label))
        pictures.append(np.concatenate(parts, axis=0))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".webm.tmp")
    tmp.write_bytes(encode_webm(pictures, FPS, [t - times[0] for t in times]))
    tmp.replace(path)


def _fit_width(pic: np.ndarray, width: int) -> np.ndarray:
    """(H, W, 3) uint8 -> (h, width, 3), the same aspect (h even)."""
    from PIL import Image

    h = max(2, round(pic.shape[0] * width / pic.shape[1]) // 2 * 2)
    return np.asarray(Image.fromarray(pic).resize((width, h), Image.Resampling.BOX))
