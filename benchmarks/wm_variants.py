"""Per-chunk planning time of the world-model variants (issue 41) side by side in one run: the preset's predictor
and the same predictor with each variant option, random weights (timing only), the default planner's search
(32 candidates x 4 iterations, KV-cached rollout; ``wamplan.planning.timing``). Prints one line per variant:
params, FLOPs of one plan (``benchmarks/profile_worldmodel.py``), seconds per chunk and the ratio to the
preset's model measured in the same run.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/wm_variants.py                 # mini, 1 thread
    .venv/bin/python benchmarks/wm_variants.py --threads 2 --repeats 5
    .venv/bin/python benchmarks/wm_variants.py --variants adaln depth6 --iterations 2
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/wm_variants.py --threads 1 --train-batch 64   # + a training step
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import platform
import statistics
import time
from pathlib import Path

import torch

from wamplan.planning.dynamics import PlanningContext
from wamplan.planning.timing import make_search
from wamplan.presets import get_world_model_preset
from wamplan.worldmodel.predictor import WorldModelPredictor

# name -> PredictorConfig changes on top of the preset's predictor
VARIANTS = {
    "preset": {},
    "adaln": dict(action_conditioning="adaln"),
    "tokens": dict(action_tokens=True),
    "adaln+tokens": dict(action_conditioning="adaln", action_tokens=True),
    "depth6": dict(depth=6),
    "width192": dict(head_dim=48, mlp_dim=576),
    "adaln+depth6": dict(action_conditioning="adaln", depth=6),
}


def _profile():
    path = Path(__file__).with_name("profile_worldmodel.py")
    spec = importlib.util.spec_from_file_location("profile_worldmodel", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def train_step_timer(model: WorldModelPredictor, batch_size: int, horizon: int = 2):
    """A function ``step() -> seconds`` timing one optimisation step of eq. 2 (K = ``horizon``) on a random batch
    of windows: the rollout with autograd, the backward pass and AdamW."""
    from wamplan.worldmodel.losses import window_loss

    cfg = model.cfg
    t = cfg.context + horizon
    g = torch.Generator().manual_seed(2)
    batch = dict(z=torch.randn(batch_size, t, cfg.num_views, cfg.num_patches, cfg.enc_dim, generator=g),
                 q=torch.randn(batch_size, t, cfg.proprio_dim, generator=g),
                 a=torch.rand(batch_size, t, cfg.action_block_dim, generator=g) * 2 - 1)
    train = model.train()
    opt = torch.optim.AdamW(train.parameters(), lr=1e-4)

    def step() -> float:
        t0 = time.perf_counter()
        loss, _ = window_loss(train, batch, horizon, 0.95)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return time.perf_counter() - t0

    return step


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="mini")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--repeats", type=int, default=5, help="timed rounds (each times every variant once)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--candidates", type=int, default=32)
    ap.add_argument("--iterations", type=int, default=4)
    ap.add_argument("--train-batch", type=int, default=0, help="also time one training step (eq. 2, K = 2) at this "
                    "batch size (the mini preset trains at 64); 0: planning only")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    base = get_world_model_preset(args.preset).predictor
    profile = _profile()
    cpu = platform.processor() or platform.machine()
    print(f"{cpu}, {torch.get_num_threads()} threads, torch {torch.__version__}, {args.preset} preset, default planner "
          f"{args.candidates} candidates x {args.iterations} iterations")
    names = ["preset", *[v for v in args.variants if v != "preset"]]
    searches, rows, steps = {}, {}, {}
    for name in names:
        cfg = dataclasses.replace(base, **VARIANTS[name])
        torch.manual_seed(0)
        model = WorldModelPredictor(cfg).eval()
        g = torch.Generator().manual_seed(1)
        ctx = PlanningContext(z=torch.randn(cfg.context, cfg.num_views, cfg.num_patches, cfg.enc_dim, generator=g),
                              q=torch.randn(cfg.context, cfg.proprio_dim, generator=g),
                              a=torch.rand(cfg.context - 1, cfg.action_block_dim, generator=g) * 2 - 1)
        target = torch.randn(cfg.num_views, cfg.num_patches, cfg.enc_dim, generator=g)
        searches[name] = make_search(model, ctx, target, candidates=args.candidates, iterations=args.iterations)
        searches[name](0)  # warm-up
        flops = profile.predictor_stats(model, args.candidates, args.iterations)["plan_flops_cached"]
        rows[name] = (model.num_params(), cfg.frame_tokens, flops, [], [])
        if args.train_batch:
            steps[name] = train_step_timer(WorldModelPredictor(cfg), args.train_batch)
            steps[name]()  # warm-up
    for r in range(args.repeats):  # interleaved rounds: a busy machine slows every variant alike
        for name in names:
            rows[name][3].append(searches[name](r + 1))
            if name in steps:
                rows[name][4].append(steps[name]())
    ref = statistics.median(rows["preset"][3])
    for name in names:
        params, tokens, flops, times, train = rows[name]
        secs = statistics.median(times)
        line = (f"{name:14s} {params / 1e6:5.2f} M params  {tokens:3d} tokens/frame  {flops / 1e9:6.2f} GFLOP/plan  "
                f"{secs:.3f} s/chunk (median of {len(times)})  {secs / ref:.2f}x the preset's")
        if train:
            line += f"  train step (batch {args.train_batch}) {statistics.median(train):.3f} s"
        print(line)


if __name__ == "__main__":
    main()
