"""What filming adds to an evaluation episode, measured side by side: each seed runs twice in one worker (one env,
one set of models), unfilmed and filmed (the order alternating seed by seed, so drift on a shared machine falls on
both), timing the whole job as the runner calls it (episode, hooks and encoding). Prints per condition the seconds
per episode without and with filming (wall-clock, and CPU seconds of the process, which other jobs move less), their
ratios, whether the two runs of every seed ended alike (filming must not change an episode) and the size on disk of
the videos per episode. The time spent inside the filming hooks and encoding (``in_filming_s``, its share of the
unfilmed time) is also timed directly; extra renders (``--video-every``) happen in the env's step and are not in it.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/videos.py --conditions 1,7 --seeds 0-3
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/videos.py --conditions 1,7 --seeds 0-3 --video-every 8
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from wamplan.config import int_list
from wamplan.evaluation.config import EvalConfig
from wamplan.evaluation.runner import VIDEO_KEY, EvalWorker
from wamplan.evaluation.videos import VideoConfig, write_episode_videos


IN_FILMING = [0.0]  # seconds spent inside the filming hooks and encoding, accumulated


def _timed(fn):
    def run(*a, **kw):
        t0 = time.perf_counter()
        try:
            return fn(*a, **kw)
        finally:
            IN_FILMING[0] += time.perf_counter() - t0
    return run


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--conditions", default="1,7")
    p.add_argument("--seeds", default="0-3")
    p.add_argument("--wam", default="checkpoints/mini/tinywam")
    p.add_argument("--wm-augmented", default="checkpoints/mini/wm_augmented")
    p.add_argument("--decoder", default="checkpoints/mini/decoder")
    p.add_argument("--video-every", type=int, default=VideoConfig.video_every)
    p.add_argument("--video-size", type=int, default=VideoConfig.video_size)
    p.add_argument("--max-steps", type=int, default=None, help="cut episodes (default: the task's 300 steps)")
    args = p.parse_args()
    from wamplan.envs.config import EnvConfig

    from wamplan.evaluation.filming import EpisodeFilm

    EpisodeFilm.__call__, EpisodeFilm.finish = _timed(EpisodeFilm.__call__), _timed(EpisodeFilm.finish)
    seeds = int_list(args.seeds, "--seeds")
    cfg = EvalConfig(wam=args.wam, wm_augmented=args.wm_augmented, env=EnvConfig(max_episode_steps=args.max_steps))
    videos = VideoConfig(videos="all", video_every=args.video_every, video_size=args.video_size, decoder=args.decoder)
    worker = EvalWorker(cfg, videos, frozenset(seeds))
    out = Path(tempfile.mkdtemp(prefix="videos_bench_"))
    conds = [int(c) for c in args.conditions.split(",")]
    for c in conds:
        worker((c, seeds[0]))  # warm-up: models, renderer, first plan
    rows = []
    for c in conds:
        plain, filmed, same, sizes, inside = [], [], [], {"episode": [], "plan": []}, []
        cpu = {False: [], True: []}  # CPU seconds of this process (every thread): less moved by other jobs
        for i, s in enumerate(seeds):
            runs = {}
            for film in ((False, True) if i % 2 == 0 else (True, False)):
                worker.filmed = frozenset(seeds) if film else frozenset()
                t0, c0, IN_FILMING[0] = time.perf_counter(), time.process_time(), 0.0
                rec = worker((c, s))
                cpu[film].append(time.process_time() - c0)
                if film:
                    inside.append(IN_FILMING[0])
                videos_made = rec.pop(VIDEO_KEY, {})
                if videos_made:
                    write_episode_videos(out, c, s, rec["variant"], rec["success"], videos_made)
                (filmed if film else plain).append(time.perf_counter() - t0)
                for k, v in videos_made.items():
                    sizes[k].append(len(v))
                runs[film] = (rec["outcome"], rec["length"], [ch.get("best_cost") for ch in rec["chunks"]])
            same.append(runs[False] == runs[True])
            print(f"cond {c} seed {s}: {plain[-1]:.1f} s unfilmed, {filmed[-1]:.1f} s filmed, {runs[True][0]} "
                  f"len {runs[True][1]}, alike {same[-1]}", flush=True)
        rows.append(dict(condition=c, seeds=len(seeds), unfilmed_s=round(float(np.mean(plain)), 2),
                         filmed_s=round(float(np.mean(filmed)), 2), ratio=round(sum(filmed) / sum(plain), 3),
                         unfilmed_cpu_s=round(float(np.mean(cpu[False])), 2),
                         filmed_cpu_s=round(float(np.mean(cpu[True])), 2),
                         cpu_ratio=round(sum(cpu[True]) / sum(cpu[False]), 3),
                         in_filming_s=round(float(np.mean(inside)), 2),
                         in_filming_share=round(sum(inside) / sum(plain), 3), alike=all(same),
                         episode_kb=round(float(np.mean(sizes["episode"])) / 1024, 1),
                         plan_kb=round(float(np.mean(sizes["plan"])) / 1024, 1) if sizes["plan"] else None))
    print(json.dumps(dict(rows=rows, video_every=args.video_every, video_size=args.video_size,
                          camera_size=cfg.env.camera_size, machine=f"{platform.node()} {platform.processor()}",
                          videos=str(out)), indent=1))


if __name__ == "__main__":
    main()
