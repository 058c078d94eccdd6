"""Which evaluation episodes are filmed, what their videos are called, and writing them into ``OUT/videos``.

    OUT/videos/c{condition}_seed{seed:04d}_{success|failure}.webm        the task's views side by side
    OUT/videos/c{condition}_seed{seed:04d}_{success|failure}_plan.webm   a planned condition: one picture per chunk
    OUT/videos/pairs/seed{seed:04d}_c{a}_vs_c{b}.webm                    `wamplan film`: two conditions side by side

A run of another first-chunk variant than the paper's (``--first-chunk rest-history``) adds ``_{variant}`` before
``.webm`` / ``_plan.webm``. :class:`VideoConfig` chooses the episodes: the first N seeds of the run's seed list
(``firstN``, default ``first4``), every episode (``all``) or none; the same command films the same seeds when it
resumes, and an episode's video is written before its record, so a resumed run neither loses nor repeats one.
The videos are settings of the run's outputs, not of its episodes: they are not stored in ``eval_config.json``.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

from wamplan.config import check_numbers, field, require

VIDEOS = "videos"  # OUT/videos
PAIRS = "pairs"  # OUT/videos/pairs
DEFAULT_VARIANT = "open-loop"  # the paper's first chunk: names without a variant suffix
FPS = 20  # the control rate: every video plays in real time
_FIRST = re.compile(r"first(\d+)")


@dataclass(frozen=True)
class VideoConfig:
    """Which episodes ``wamplan eval`` films, and how."""

    videos: str = field("first4", "episodes filmed, as OUT/videos/c{condition}_seed{seed:04d}_{success|failure}"
                        ".webm (and _plan.webm for a planned condition): firstN (the first N seeds of the run, every "
                        "condition, e.g. first4), all, or none", listed=("firstN", "all", "none"))
    video_every: int = field(0, "also film a frame every this many control steps (each costs a render of every "
                             "camera); 0: only the frames the policy renders anyway (every "
                             "chunk boundary, a world model's history frames) and the last, one render an episode")
    video_size: int = field(160, "side in pixels of each view in the videos (an even number)")
    decoder: str = field("", "picture decoder (`wamplan wm train-decoder`) that draws the world model's predictions "
                         "in a planned condition's plan video; without it the plan video shows the real views and "
                         "the WAM's target alone")

    def __post_init__(self):
        check_numbers(self)
        require(self.videos in ("all", "none") or bool(_FIRST.fullmatch(self.videos)),
                f"--videos '{self.videos}' is not firstN (e.g. first4), all or none")
        require(self.video_every >= 0, f"--video-every {self.video_every} must be >= 0 (0: no extra renders)")
        require(self.video_size >= 16 and self.video_size % 2 == 0,
                f"--video-size {self.video_size} must be an even number of pixels >= 16, e.g. 160")

    @property
    def first(self) -> int | None:
        """How many leading seeds are filmed: None for all, 0 for none."""
        if self.videos == "all":
            return None
        return 0 if self.videos == "none" else int(_FIRST.fullmatch(self.videos).group(1))

    def filmed(self, seeds: Iterable[int]) -> frozenset[int]:
        """The seeds filmed of a run over ``seeds`` (in the order given)."""
        seeds = list(seeds)
        return frozenset(seeds if self.first is None else seeds[:self.first])


def variant_of(rec: dict[str, Any]) -> str:
    """The first-chunk variant a record's videos are named by (records written before variants existed, and
    ``records.record_key``'s "default", ran the paper's)."""
    v = rec.get("variant", DEFAULT_VARIANT)
    return DEFAULT_VARIANT if v == "default" else str(v)


def video_name(condition: int, seed: int, success: bool, variant: str = DEFAULT_VARIANT, plan: bool = False) -> str:
    """``c7_seed0003_success.webm`` (``..._plan.webm`` with ``plan``); another variant adds ``_{variant}``."""
    tail = ("" if variant == DEFAULT_VARIANT else f"_{variant}") + ("_plan" if plan else "")
    return f"c{condition}_seed{seed:04d}_{'success' if success else 'failure'}{tail}.webm"


def pair_name(seed: int, a: int, b: int) -> str:
    return f"seed{seed:04d}_c{a}_vs_c{b}.webm"


PAIR_NAME = re.compile(r"seed(\d+)_c(\d+)_vs_c(\d+)\.webm")  # pair_name's (seed, a, b) read back


def episode_videos(out: str | Path, condition: int, seed: int, variant: str = DEFAULT_VARIANT) -> list[Path]:
    """The videos ``out/videos`` holds of one episode (either outcome, with its plan video)."""
    d = Path(out) / VIDEOS
    return [d / video_name(condition, seed, ok, variant, plan) for ok in (True, False) for plan in (False, True)
            if (d / video_name(condition, seed, ok, variant, plan)).is_file()]


def require_video_dir(out: str | Path) -> Path:
    """``out/videos`` as a directory to write into; one line (before any episode runs) if it cannot be."""
    from wamplan.errors import UserError, require_writable

    p = Path(out) / VIDEOS
    if p.exists() and not p.is_dir():
        raise UserError(f"the video directory {p} is a file, so no video can be written; move it away, or pass "
                        f"--videos none")
    require_writable(p, "the video directory", "make it writable, or pass --videos none")
    return p


def write_episode_videos(out: str | Path, condition: int, seed: int, variant: str, success: bool,
                         videos: dict[str, bytes]) -> list[Path]:
    """Write an episode's encoded videos (``"episode"`` / ``"plan"`` -> WebM bytes) under their names, each
    through a temporary file, after removing the episode's videos of the other outcome (a re-run on another
    machine) -> the paths written."""
    d = Path(out) / VIDEOS
    d.mkdir(parents=True, exist_ok=True)
    for old in episode_videos(out, condition, seed, variant):
        old.unlink()
    paths = []
    for kind, data in videos.items():
        path = d / video_name(condition, seed, success, variant, plan=kind == "plan")
        tmp = path.with_suffix(".webm.tmp")
        tmp.write_bytes(data)
        os.replace(tmp, path)
        paths.append(path)
    return paths


def plan_video_note(videos: VideoConfig, conditions: Iterable[int], oracle_blend: float = 0.0) -> str | None:
    """The one line that says which plan videos will show no world-model predictions, and why (None: all will, or
    none is filmed)."""
    from wamplan.evaluation.conditions import CONDITIONS

    if videos.first == 0:
        return None
    planned = [c for c in conditions if CONDITIONS[c].dynamics != "none"]
    learned = [c for c in planned if CONDITIONS[c].learned]
    sim = [c for c in planned if not CONDITIONS[c].learned]
    why = []
    if learned and oracle_blend > 0:
        why.append(f"conditions {learned} plan with --oracle-blend (the simulator steps in their predictions)")
    elif learned and not videos.decoder:
        why.append(f"condition{'s' if len(learned) > 1 else ''} {', '.join(map(str, learned))}: no --decoder given "
                   f"(pass one made by `wamplan wm train-decoder` to draw the world model's predictions)")
    if sim:
        why.append(f"condition{'s' if len(sim) > 1 else ''} {', '.join(map(str, sim))} plan in the simulator, which "
                   f"has no decoder")
    if not why:
        return None
    return "plan videos show the real views and the WAM's target without model predictions: " + "; ".join(why)


def write_record_videos(out: str | Path, rec: dict[str, Any], videos: dict[str, bytes] | None,
                        error: str | None) -> None:
    """Write the ``videos`` a filmed episode's record ``rec`` came with into ``out/videos``; a video that could not
    be made (``error``) or written says so in one line on stderr, and the record is kept."""
    import sys

    from wamplan.errors import reason

    try:
        if videos:
            write_episode_videos(out, rec["condition"], rec["seed"], variant_of(rec), bool(rec["success"]), videos)
    except OSError as e:
        error = reason(e)
    if error:
        print(f"warning: condition {rec['condition']} seed {rec['seed']} was not filmed ({error}); its record is "
              f"kept", file=sys.stderr)
