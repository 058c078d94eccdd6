"""The world-model recipe of ``lab/wm-variants/wm_variants.sh`` at scale on one machine with a GPU, in one command.

    python lab/wm-variants/wm_scale.py OUT                         # on a GPU machine: every core collects, the GPU trains
    python lab/wm-variants/wm_scale.py OUT --variant adaln="--action-conditioning adaln --epochs 12" \
        --variant dct="--action-conditioning adaln --epochs 12 --encoder-kwargs '{\"basis\": \"dct\"}'"
    python lab/wm-variants/wm_scale.py OUT --collect-seconds 60 --workers 2 --render-backend cpu --device cpu \
        --epochs 1 --variant mini=""                       # a small rehearsal on a CPU machine

1. Collection for a fixed time (``--collect-seconds``) on ``--workers`` simulator processes, shared among the
   recipe's four sources in its proportions: the scripted expert (seeds 20000-), the noisy expert (30000-),
   pink noise (40000-, 100 steps) and the policy ``--policy`` with ``--branches`` counterfactual branches at
   every chunk boundary (50000-). When the time is up the collectors are stopped; an episode is kept only
   when its file was complete (``EpisodeStore`` writes under a temporary name), so a cut-off run is still a
   valid training set. ``--collect-seconds 0`` collects nothing.
2. ``wamplan wm encode`` of the four stores in parallel, once for every encoder setting the variants use
   (``--encoder-kwargs`` in a variant's flags).
3. ``wamplan wm train`` of every ``--variant NAME=FLAGS`` side by side on the one GPU, on the same stores, each
   with the ``mini`` preset overridden by its FLAGS (default: one variant ``wide``, a larger predictor than the
   preset's) and a share of the cores as data-loading workers; each is stopped with Ctrl-C's checkpoint after
   ``--train-seconds`` if it has not finished its epochs.
4. Each checkpoint exported for inference in float16 (``OUT/export/NAME``, small enough to copy back), and
   ``OUT/summary.json``: one entry per invocation with the episodes per source, seconds per stage, and each
   variant's flags, epochs it was set to, exit status and last metrics (the epoch it reached).

Re-running the same command resumes: while a variant's run ``OUT/runs/NAME`` holds a checkpoint, collection and
encoding are skipped (the trainings resume only on unchanged stores) and each training goes on from its
checkpoint. Score an export on the benchmark store with ``wamplan wm eval --ckpt OUT/export/NAME --data
data/wm_bench --split all --horizon 4``.

Seeds stay clear of the test (0-99), validation (500-599), benchmark (9000-9031) and other training ranges.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

from wamplan.errors import UserError
from wamplan.train_loop import saved_progress

# source, its --seed-start, its share of the workers, extra collect flags; the shares follow the recipe's
# episode counts (100 expert, 100 noisy, 150 pink, 50 parents with 6 branches per chunk boundary, the slowest)
SOURCES = (("expert", 20000, 2, ()), ("noisy-expert", 30000, 2, ()),
           ("pink", 40000, 3, ("--max-steps", "100")), ("policy", 50000, 8, ()))
# width 384 (the preset's 128), depth 4: 6.1 M params, 8.4x the preset's
DEFAULT_VARIANT = "wide=--heads 8 --head-dim 48 --mlp-dim 1152"


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


def variant(spec: str) -> tuple[str, list[str]]:
    """``NAME=FLAGS`` -> (NAME, FLAGS split as a shell would)."""
    name, sep, flags = spec.partition("=")
    if not sep or not name or "/" in name:
        raise argparse.ArgumentTypeError(f"--variant {spec!r}: write NAME=FLAGS, "
                                         f"e.g. adaln='--action-conditioning adaln'")
    return name, shlex.split(flags)


def encoder_setting(flags: list[str]) -> str:
    """The ``--encoder-kwargs`` of a variant's flags as one canonical JSON object (``"{}"``: the preset's encoder),
    so that spellings of the same setting share one encoding of the stores."""
    spec = "{}"
    for i, arg in enumerate(flags):
        if arg == "--encoder-kwargs" and i + 1 < len(flags):
            spec = flags[i + 1]
        elif arg.startswith("--encoder-kwargs="):
            spec = arg.split("=", 1)[1]
    try:
        kw = json.loads(spec)
    except json.JSONDecodeError as e:
        raise argparse.ArgumentTypeError(f"--encoder-kwargs {spec!r} is not JSON ({e})")
    if not isinstance(kw, dict):
        raise argparse.ArgumentTypeError(f"--encoder-kwargs {spec!r} must be a JSON object")
    return json.dumps(kw, sort_keys=True)


def features_of(setting: str) -> str:
    """The feature-cache key of the mini preset's encoder with ``setting`` (JSON) over its settings."""
    from wamplan.data.features import feature_key
    from wamplan.encoders import make_encoder
    from wamplan.presets import get_world_model_preset

    preset = get_world_model_preset("mini")
    return feature_key(make_encoder(preset.encoder, **{**preset.encoder_kwargs, **json.loads(setting)}).config_dict())


def encode(out: Path, args: argparse.Namespace) -> None:
    """Each encoder setting the variants use over each store, all in parallel (reading the images is the cost);
    features already cached are kept, so this is quick on a resume."""
    wanted = (encoder_setting(flags) for _, flags in args.variant)
    settings = sorted({features_of(s): s for s in wanted}.values())  # one per feature cache: no two writers of one
    procs = []
    for k, setting in enumerate(settings):
        for s in SOURCES:
            with open(out / f"encode-{s[0]}-{k}.log", "a") as log:
                procs.append(subprocess.Popen(wamplan("wm", "encode", "--data", str(out / "data" / s[0]), "--preset",
                                                      "mini", "--device", args.device, "--encoder-kwargs", setting),
                                              stdout=log, stderr=subprocess.STDOUT))
    if any([p.wait() for p in procs]):  # every one waited for
        raise SystemExit(f"encoding failed: see {out}/encode-<source>-<k>.log")


def train(out: Path, args: argparse.Namespace) -> dict[str, int]:
    """Every variant side by side until done or ``--train-seconds``; the exit status of each. However this ends
    (the deadline, Ctrl-C, an error), every training still running is stopped with its Ctrl-C checkpoint."""
    data = ",".join(str(out / "data" / s[0]) for s in SOURCES)
    loaders = max(0, args.workers // len(args.variant) - 1)  # data-loading workers per training
    procs: dict[str, subprocess.Popen] = {}
    status: dict[str, int] = {}
    try:
        for name, flags in args.variant:
            cmd = wamplan("wm", "train", "--data", data, "--preset", "mini", "--out", str(out / "runs" / name),
                          "--epochs", str(args.epochs), "--device", args.device, "--save-every-steps", "500",
                          "--num-workers", str(loaders), *flags)
            with open(out / f"train-{name}.log", "a") as log:
                # SIGINT at its default, so Python turns it into KeyboardInterrupt even where this script was
                # started with SIGINT ignored (a background job of a shell)
                procs[name] = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT,
                                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        deadline = time.time() + args.train_seconds
        while time.time() < deadline and any(p.poll() is None for p in procs.values()):
            time.sleep(2)
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)  # the training loop checkpoints on Ctrl-C
        for name, p in procs.items():
            try:
                status[name] = p.wait(timeout=120)
            except subprocess.TimeoutExpired:
                p.kill()
                status[name] = p.wait()
    return status


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path, help="output directory (data/, runs/, export/, summary.json)")
    ap.add_argument("--collect-seconds", type=float, default=180.0, help="collection time (0: collect nothing)")
    ap.add_argument("--train-seconds", type=float, default=240.0,
                    help="training time, after which it stops with a checkpoint (re-run to go on)")
    ap.add_argument("--workers", type=int, default=max(1, len(os.sched_getaffinity(0)) - 1),
                    help="simulator processes in all, at least one per source, and then the processes of the "
                         "trainings: each variant gets workers / variants - 1 data-loading workers (default: "
                         "cores - 1)")
    ap.add_argument("--render-backend", default="gpu", help="ManiSkill render backend of the collectors")
    ap.add_argument("--device", default="cuda", help="torch device of the training")
    ap.add_argument("--policy", default="checkpoints/mini/tinywam", help="the WAM whose episodes are branched")
    ap.add_argument("--branches", type=int, default=6)
    ap.add_argument("--epochs", type=int, default=4,
                    help="passes over the collected data (the recipe's: 4); a variant's own --epochs wins")
    ap.add_argument("--variant", action="append", type=variant, default=None, metavar="NAME=FLAGS",
                    help="a model to train: NAME and its `wamplan wm train` flags ('' for the preset's); repeat to "
                         "train several side by side (default: " + DEFAULT_VARIANT + ")")
    args = ap.parse_args()
    args.variant = args.variant or [variant(DEFAULT_VARIANT)]
    for _, flags in args.variant:
        try:
            features_of(encoder_setting(flags))  # the setting parses and builds an encoder
        except (argparse.ArgumentTypeError, UserError) as e:
            ap.error(f"--variant: {e}")
    if len({name for name, _ in args.variant}) < len(args.variant):
        ap.error("--variant: every NAME once")
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    seconds: dict[str, float] = {}

    resuming = any(saved_progress(out / "runs" / name) is not None for name, _ in args.variant)
    if resuming:  # the stores must stay as the checkpoints' trainings saw them
        print(f"{out / 'runs'} holds a checkpoint: no collection; trainings with a checkpoint resume", flush=True)
    t = time.time()
    counts = collect(out, args, 0 if resuming else args.collect_seconds)
    seconds["collect"] = time.time() - t
    print(f"{counts} episodes after {seconds['collect']:.0f} s of collection", flush=True)

    t = time.time()
    encode(out, args)  # also on a resume: a new variant's encoder, or nothing to do
    seconds["encode"] = time.time() - t

    t = time.time()
    status = train(out, args)
    seconds["train"] = time.time() - t
    print(f"trainings exited with {status} after {seconds['train']:.0f} s", flush=True)

    variants = {}
    for name, flags in args.variant:
        run = out / "runs" / name
        entry = {"flags": shlex.join(flags), "train_exit": status[name], "exported": False, "last_metrics": None}
        variants[name] = entry
        if status[name] not in (0, 130) or saved_progress(run) is None:  # one failure leaves the others' exports
            print(f"training {name} failed (exit {status[name]}) or saved no checkpoint: see {out}/train-{name}.log",
                  file=sys.stderr, flush=True)
            continue
        done = subprocess.run([sys.executable, "-c", "import sys; from wamplan.checkpoint import export_for_inference; "
                               "export_for_inference(sys.argv[1], sys.argv[2])", str(run / "checkpoint"),
                               str(out / "export" / name)])
        metrics = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines() if line]
        saved = json.loads((run / "checkpoint" / "config.json").read_text())["config"]["train"]
        entry.update(exported=done.returncode == 0, last_metrics=metrics[-1] if metrics else None,
                     epochs=saved["epochs"])  # the epochs it was set to (its own --epochs wins over the script's)
        if done.returncode:
            print(f"export of {name} failed (exit {done.returncode})", file=sys.stderr, flush=True)
    record = {"episodes": counts, "seconds": seconds, "default_epochs": args.epochs, "workers": args.workers,
              "resumed": resuming, "variants": variants}
    path = out / "summary.json"
    runs = json.loads(path.read_text())["runs"] if path.exists() else []
    path.write_text(json.dumps({"runs": runs + [record]}, indent=1))
    print(json.dumps(record), flush=True)
    return 0 if all(v["exported"] for v in variants.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
