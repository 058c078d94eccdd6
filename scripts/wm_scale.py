"""The world-model recipe of ``scripts/wm_variants.sh`` at scale on one machine with a GPU, in one command.

    python scripts/wm_scale.py OUT                         # on a GPU machine: every core collects, the GPU trains
    python scripts/wm_scale.py OUT --collect-seconds 60 --workers 2 --render-backend cpu --device cpu \
        --epochs 1 --arch ""                               # a small rehearsal on a CPU machine

1. Collection for a fixed time (``--collect-seconds``) on ``--workers`` simulator processes, shared among the
   recipe's four sources in its proportions: the scripted expert (seeds 20000-), the noisy expert (30000-),
   pink noise (40000-, 100 steps) and the policy ``--policy`` with ``--branches`` counterfactual branches at
   every chunk boundary (50000-). When the time is up the collectors are stopped; an episode is kept only
   when its file was complete (``EpisodeStore`` writes under a temporary name), so a cut-off run is still a
   valid training set. ``--collect-seconds 0`` collects nothing.
2. ``wamplan wm encode`` of the four stores in parallel, then ``wamplan wm train`` on them with the ``mini``
   preset and ``--arch``'s predictor flags (a larger predictor than the preset's by default), on ``--device``;
   stopped with Ctrl-C's checkpoint after ``--train-seconds`` if it has not finished its epochs.
3. The checkpoint exported for inference in float16 (``OUT/export``, small enough to copy back), and
   ``OUT/summary.json``: one entry per invocation with the episodes per source, seconds per stage, the
   architecture and the training's last metrics.

Re-running the same command resumes: while ``OUT/run`` holds a checkpoint, collection and encoding are skipped
(the training resumes only on unchanged stores) and the training goes on from its checkpoint. Score the export on the benchmark store with ``wamplan wm eval --ckpt OUT/export --data
   data/wm_bench --split all --horizon 4``.

Seeds stay clear of the test (0-99), validation (500-599), benchmark (9000-9031) and other training ranges.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from wamplan.train_loop import saved_progress

# source, its --seed-start, its share of the workers, extra collect flags; the shares follow the recipe's
# episode counts (100 expert, 100 noisy, 150 pink, 50 parents with 6 branches per chunk boundary, the slowest)
SOURCES = (("expert", 20000, 2, ()), ("noisy-expert", 30000, 2, ()),
           ("pink", 40000, 3, ("--max-steps", "100")), ("policy", 50000, 8, ()))
DEFAULT_ARCH = "--heads 8 --head-dim 48 --mlp-dim 1152"  # width 384 (the preset's 128), depth 4: 6.1 M params, 8.4x


def wamplan(*args: str) -> list[str]:
    return [sys.executable, "-m", "wamplan.cli", *args]


def split_workers(total: int) -> list[int]:
    """Workers per source, in proportion to the shares, at least one each: ``max(total, len(SOURCES))`` in all."""
    shares = [s[2] for s in SOURCES]
    want = [max(total, len(shares)) * s / sum(shares) for s in shares]
    counts = [max(1, int(w)) for w in want]
    while sum(counts) > max(total, len(shares)):  # the at-least-one floors overshot: take from the largest
        counts[counts.index(max(counts))] -= 1
    while sum(counts) < total:  # the remainder to the largest shortfall
        short = [w - c for w, c in zip(want, counts)]
        counts[short.index(max(short))] += 1
    return counts


def collect(out: Path, args: argparse.Namespace, seconds: float) -> dict[str, int]:
    """Collect for ``seconds`` (0: none); the episodes per source in the stores."""
    procs = []
    try:
        if seconds > 0:
            for (source, seed, _, extra), workers in zip(SOURCES, split_workers(args.workers)):
                cmd = wamplan("collect", "--source", source, "--episodes", "9999", "--seed-start", str(seed),
                              "--out", str(out / "data" / source), "--workers", str(workers),
                              "--render-backend", args.render_backend, *extra)
                if source == "policy":
                    cmd += ["--policy", args.policy, "--branches", str(args.branches)]
                with open(out / f"collect-{source}.log", "a") as log:
                    procs.append(subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True))
                print(f"collect {source}: {workers} workers, seeds from {seed}", flush=True)
        deadline = time.time() + seconds
        while time.time() < deadline and any(p.poll() is None for p in procs):
            time.sleep(2)
    finally:  # also on Ctrl-C or an error: no collector outlives this script
        for p in procs:  # each collector and its workers are one process group
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
    counts = {s[0]: len(list((out / "data" / s[0] / "episodes").glob("*.h5"))) for s in SOURCES}
    bad = [s for s, n in counts.items() if n == 0]
    if bad:
        raise SystemExit(f"no episode of {', '.join(bad)} was collected in {seconds} s: see "
                         f"{out}/collect-<source>.log")
    return counts


def encode(out: Path, args: argparse.Namespace) -> None:
    """The preset's encoder over each store, the four in parallel (reading the images is the cost)."""
    procs = []
    for s in SOURCES:
        with open(out / f"encode-{s[0]}.log", "a") as log:
            procs.append(subprocess.Popen(wamplan("wm", "encode", "--data", str(out / "data" / s[0]), "--preset",
                                                  "mini", "--device", args.device), stdout=log, stderr=subprocess.STDOUT))
    if any([p.wait() for p in procs]):  # every one waited for
        raise SystemExit(f"encoding failed: see {out}/encode-<source>.log")


def train(out: Path, args: argparse.Namespace) -> int:
    data = ",".join(str(out / "data" / s[0]) for s in SOURCES)
    cmd = wamplan("wm", "train", "--data", data, "--preset", "mini", "--out", str(out / "run"), "--epochs",
                  str(args.epochs), "--device", args.device, "--save-every-steps", "500", *args.arch.split())
    with open(out / "train.log", "a") as log:
        # SIGINT at its default, so Python turns it into KeyboardInterrupt even where this script was started
        # with SIGINT ignored (a background job of a shell)
        p = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT,
                             preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        try:
            return p.wait(timeout=args.train_seconds)
        except subprocess.TimeoutExpired:
            p.send_signal(signal.SIGINT)  # the training loop checkpoints on Ctrl-C
            try:
                return p.wait(timeout=120)
            except subprocess.TimeoutExpired:
                p.kill()
                return p.wait()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path, help="output directory (data/, run/, export/, summary.json)")
    ap.add_argument("--collect-seconds", type=float, default=180.0, help="collection time (0: collect nothing)")
    ap.add_argument("--train-seconds", type=float, default=240.0,
                    help="training time, after which it stops with a checkpoint (re-run to go on)")
    ap.add_argument("--workers", type=int, default=max(1, len(os.sched_getaffinity(0)) - 1),
                    help="simulator processes in all, at least one per source (default: cores - 1)")
    ap.add_argument("--render-backend", default="gpu", help="ManiSkill render backend of the collectors")
    ap.add_argument("--device", default="cuda", help="torch device of the training")
    ap.add_argument("--policy", default="checkpoints/mini/tinywam", help="the WAM whose episodes are branched")
    ap.add_argument("--branches", type=int, default=6)
    ap.add_argument("--epochs", type=int, default=4, help="passes over the collected data (the recipe's: 4)")
    ap.add_argument("--arch", default=DEFAULT_ARCH, help="predictor flags of `wamplan wm train` ('' for the preset's)")
    args = ap.parse_args()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    seconds: dict[str, float] = {}

    resuming = saved_progress(out / "run") is not None
    if resuming:  # the stores must stay as the checkpoint's training saw them
        print(f"{out / 'run'} holds a checkpoint: no collection, the training resumes", flush=True)
    t = time.time()
    counts = collect(out, args, 0 if resuming else args.collect_seconds)
    seconds["collect"] = time.time() - t
    print(f"{counts} episodes after {seconds['collect']:.0f} s of collection", flush=True)

    if not resuming:
        t = time.time()
        encode(out, args)
        seconds["encode"] = time.time() - t

    t = time.time()
    status = train(out, args)
    seconds["train"] = time.time() - t
    print(f"training exited with {status} after {seconds['train']:.0f} s", flush=True)
    if status not in (0, 130) or saved_progress(out / "run") is None:
        raise SystemExit(f"training failed (exit {status}) or saved no checkpoint: see {out}/train.log")

    t = time.time()
    subprocess.run([sys.executable, "-c", "import sys; from wamplan.checkpoint import export_for_inference; "
                    "export_for_inference(sys.argv[1], sys.argv[2])", str(out / "run" / "checkpoint"),
                    str(out / "export")], check=True)
    seconds["export"] = time.time() - t
    metrics = [json.loads(line) for line in (out / "run" / "metrics.jsonl").read_text().splitlines() if line]
    entry = {"episodes": counts, "seconds": seconds, "arch": args.arch, "epochs": args.epochs, "workers": args.workers,
             "resumed": resuming, "train_exit": status, "last_metrics": metrics[-1] if metrics else None}
    path = out / "summary.json"
    runs = json.loads(path.read_text())["runs"] if path.exists() else []
    path.write_text(json.dumps({"runs": runs + [entry]}, indent=1))
    print(json.dumps(entry), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
