"""Collect the world-model benchmark store (issue 41): counterfactual sibling groups at every chunk boundary of
held-out episodes, so every phase of the task (grasp, carry, alignment, descent) has groups to score.

    .venv/bin/python scripts/wm_benchmark_store.py --out data/wm_bench            # collect (resumable)
    .venv/bin/python scripts/wm_benchmark_store.py --out data/wm_bench --check    # fingerprint, phases only
    .venv/bin/wamplan wm eval --ckpt CKPT --data data/wm_bench --split all --horizon 4

The benchmark is this one command (``BENCHMARK``; any other value makes another benchmark, and the script
says so):

    wamplan collect --source policy --policy checkpoints/mini/tinywam --plan-with checkpoints/mini/wm_augmented
        --episodes 32 --seed-start 9000 --branches 8 --branch-sigmas 0.03 0.06 0.1 --branch-context 8
        --max-steps 192 --camera-size 224 --image-every 4 --out DIR --workers W

Condition 7's planned policy (the shipped TinyWAM planning in the shipped ``wm_augmented``) runs seeds
9000-9031 (no run in docs/ used them: test 0-99, validation 500-649, collections 1000-5349),
truncated at 192 steps, so the boundaries 16, 32, ..., 176 cover the approach and grasp, the carry, the
hovering over the mount and the descent. At each boundary 8 branches execute the planned chunk plus Gaussian
noise of std 0.03, 0.06, 0.1 (cycled; CEM's sigma is 0.1), from a restored snapshot. Branch j of parent s is
seed s * 1000 + j. Each seed's episode and branches depend on the seed alone, so the worker count does not
change the data; re-runs on one machine record the same trajectories (the printed fingerprint, a hash of the
recorded states, says so). Another machine may differ slightly (PhysX and the renderer; docs/results.md,
"Reproducibility across machines"): compare models on a store collected on one machine.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

BENCHMARK = dict(source="policy", policy="checkpoints/mini/tinywam", plan_with="checkpoints/mini/wm_augmented",
                 episodes=32, seed_start=9000, branches=8, branch_sigmas=(0.03, 0.06, 0.1), branch_context=8,
                 max_steps=192, camera_size=224, image_every=4)


def collect_argv(out: str, workers: int, settings: dict) -> list[str]:
    """``wamplan collect``'s arguments for ``settings`` (keys of :data:`BENCHMARK`)."""
    s = settings
    plan = ["--plan-with", s["plan_with"]] if s["plan_with"] else []
    return ["collect", "--source", s["source"], "--policy", s["policy"], *plan, "--episodes", str(s["episodes"]),
            "--seed-start", str(s["seed_start"]), "--branches", str(s["branches"]),
            "--branch-sigmas", *map(str, s["branch_sigmas"]), "--branch-context", str(s["branch_context"]),
            "--max-steps", str(s["max_steps"]), "--camera-size", str(s["camera_size"]),
            "--image-every", str(s["image_every"]), "--out", out, "--workers", str(workers)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="the store directory (created, or resumed)")
    ap.add_argument("--workers", type=int, default=2, help="simulator processes (does not change the data)")
    ap.add_argument("--check", action="store_true", help="collect nothing: print the store's fingerprint and phases")
    for key, value in BENCHMARK.items():  # for smoke tests only: a changed value is another benchmark
        flag = "--" + key.replace("_", "-")
        kind = type(value[0]) if isinstance(value, tuple) else type(value)
        ap.add_argument(flag, type=kind, nargs="+" if isinstance(value, tuple) else None, default=value,
                        help=f"(default, the benchmark's: {value})")
    args = ap.parse_args(argv)
    settings = {k: tuple(v) if isinstance(v, list) else v for k, v in vars(args).items() if k in BENCHMARK}
    changed = {k: v for k, v in settings.items() if v != BENCHMARK[k]}
    if changed:
        print(f"NOT the benchmark store: {changed} differ from scripts/wm_benchmark_store.py's BENCHMARK")
    start = time.perf_counter()
    if not args.check:
        from wamplan.cli import main as wamplan

        if (rc := wamplan(collect_argv(args.out, args.workers, settings))) != 0:
            return rc
    from wamplan.worldmodel.benchmark import phase_counts, store_fingerprint

    from wamplan.cli.data import store_info

    info = store_info(args.out)
    print(json.dumps(dict(store=args.out, episodes=info["episodes"], bytes=info["bytes"],
                          seconds=round(time.perf_counter() - start, 1), groups=phase_counts(args.out),
                          fingerprint=store_fingerprint(args.out), benchmark=not changed), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
