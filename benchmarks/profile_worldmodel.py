"""Parameter counts, FLOPs and planning-rollout timings of the world-model presets.

FLOPs are counted with ``torch.utils.flop_counter.FlopCounterMode`` on meta tensors (no memory, no
weights needed; multiply-add = 2 FLOPs; matmuls and attention only, elementwise ops are not counted).

    .venv/bin/python benchmarks/profile_worldmodel.py            # both presets' figures, mini timings
    .venv/bin/python benchmarks/profile_worldmodel.py --threads 1
"""

from __future__ import annotations

import argparse
import statistics
import time
from typing import Any

import torch
from torch.utils.flop_counter import FlopCounterMode

from wamplan.planning.timing import sync
from wamplan.worldmodel.decoder import Decoder
from wamplan.worldmodel.predictor import WorldModelPredictor
from wamplan.presets import PRESETS, get_world_model_preset as get_preset

CHUNK = 16  # actions per WAM chunk


def _inputs(model: WorldModelPredictor, batch: int, frames: int, device: torch.device | str):
    c = model.cfg
    z = torch.randn(batch, frames, c.num_views, c.num_patches, c.enc_dim, device=device)  # (B, T, V, N, D)
    q = torch.randn(batch, frames, c.proprio_dim, device=device)  # (B, T, P)
    a = torch.randn(batch, frames, c.action_block_dim, device=device)  # (B, T, Delta*A)
    return z, q, a


def _count(fn) -> int:
    with FlopCounterMode(display=False) as counter:
        fn()
    return int(counter.get_total_flops())


def plan_once(model: WorldModelPredictor, z: torch.Tensor, q: torch.Tensor, a: torch.Tensor,
              candidates: int, iterations: int, steps: int, naive: bool = False) -> None:
    """The world-model work of one CEM plan: context (1, H_ctx, ...) shared, ``iterations`` rollouts
    of ``candidates`` x ``steps`` frames (the cost and the CEM update are negligible next to it)."""
    a_future = torch.randn(candidates, steps, a.shape[-1], device=a.device)  # (C, S, Delta*A)
    if naive:
        for _ in range(iterations):
            model.rollout(z, q, a[:, :-1], a_future, naive=True)
        return
    prefix = model.encode_prefix(z[:, :-1], q[:, :-1], a[:, :-1])  # once per chunk
    for _ in range(iterations):
        model.rollout_from_prefix(prefix, z[:, -1], q[:, -1], a_future)  # (C, S, V, N, D), (C, S, P)


def predictor_stats(model: WorldModelPredictor, candidates: int = 32, iterations: int = 4) -> dict[str, Any]:
    """Params and FLOPs of a predictor (pass one built on the meta device to skip allocating weights)."""
    c = model.cfg
    dev = next(model.parameters()).device
    steps = CHUNK // c.frameskip
    z, q, a = _inputs(model, 1, c.context, dev)
    with torch.no_grad():
        fwd = _count(lambda: model(z, q, a))
        plan = _count(lambda: plan_once(model, z, q, a, candidates, iterations, steps))
        plan_naive = _count(lambda: plan_once(model, z, q, a, candidates, iterations, steps, naive=True))
    return {"params": sum(p.numel() for p in model.parameters()), "tokens_per_frame": c.tokens_per_frame,
            "forward_flops": fwd, "forward_frames": c.context, "rollout_steps_per_chunk": steps,
            "plan_flops_cached": plan, "plan_flops_naive": plan_naive}


def preset_stats(name: str) -> dict[str, Any]:
    """Predictor and decoder params/FLOPs of a preset, with random (meta) weights."""
    p = get_preset(name)
    with torch.device("meta"):
        pred = WorldModelPredictor(p.predictor)
        dec = Decoder(p.decoder)
    with torch.no_grad():
        zd = torch.randn(1, p.decoder.num_patches, p.decoder.enc_dim, device="meta")  # (1, N, D)
        dec_flops = _count(lambda: dec(zd))
    return {"preset": name, "predictor": predictor_stats(pred),
            "decoder": {"params": sum(t.numel() for t in dec.parameters()), "forward_flops_one_view": dec_flops}}


def time_plan(model: WorldModelPredictor, candidates: int = 32, iterations: int = 4, naive: bool = False,
              repeats: int = 5) -> tuple[float, float]:
    """Median wall time and median process CPU time (s) of ``plan_once`` on the model's device, after
    one warm-up. On a CPU shared with other jobs the CPU time (with 1 thread) is the better estimate of
    what an idle core would take; on an accelerator only the wall time means anything."""
    c = model.cfg
    dev = next(model.parameters()).device
    z, q, a = _inputs(model, 1, c.context, dev)
    walls, cpus = [], []
    with torch.inference_mode():
        for i in range(repeats + 1):
            sync(dev)
            t0, c0 = time.perf_counter(), time.process_time()
            plan_once(model, z, q, a, candidates, iterations, CHUNK // c.frameskip, naive)
            sync(dev)
            if i:
                walls.append(time.perf_counter() - t0)
                cpus.append(time.process_time() - c0)
    return statistics.median(walls), statistics.median(cpus)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--time", nargs="*", default=["mini"], help="presets to time on this machine's CPU")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    for name in PRESETS:
        s = preset_stats(name)
        pr, de = s["predictor"], s["decoder"]
        print(f"[{name}] predictor {pr['params'] / 1e6:.2f} M params; forward over {pr['forward_frames']} frames "
              f"x {pr['tokens_per_frame']} tokens (batch 1): {pr['forward_flops'] / 1e9:.2f} GFLOP; "
              f"one CEM plan (32 x 4 iters x {pr['rollout_steps_per_chunk']} steps): "
              f"{pr['plan_flops_cached'] / 1e9:.1f} GFLOP cached, {pr['plan_flops_naive'] / 1e9:.1f} GFLOP naive")
        print(f"[{name}] decoder {de['params'] / 1e6:.2f} M params; "
              f"{de['forward_flops_one_view'] / 1e9:.2f} GFLOP / view")
    torch.manual_seed(0)
    for name in args.time:
        model = WorldModelPredictor(get_preset(name).predictor).eval()
        (cw, cc), (nw, nc) = time_plan(model, repeats=args.repeats), time_plan(model, naive=True, repeats=args.repeats)
        print(f"[{name}] one CEM plan on {torch.get_num_threads()} CPU thread(s): KV-cached {cw * 1e3:.0f} ms wall "
              f"({cc * 1e3:.0f} ms CPU), naive {nw * 1e3:.0f} ms wall ({nc * 1e3:.0f} ms CPU); "
              f"naive / cached = {nw / cw:.1f}x")


if __name__ == "__main__":
    main()
