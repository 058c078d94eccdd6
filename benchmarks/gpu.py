"""One prepared GPU run (issue 42): paper-preset planning per chunk, DINOv3 ViT-L/16 throughput and predictor
training speed, fp32 and bf16 side by side, written as one JSON and one Markdown table into ``--out``.

    benchmarks/gpu.sh --out out/gpu                                   # full size on a GPU (~5-8 min on an H200)
    .venv/bin/python benchmarks/gpu.py --tiny --device cpu --out /tmp/gpu   # tiny sizes: wiring, not speed
    benchmarks/gpu.sh --sections matmul plan --plan-modes eager           # a subset

Parts (``--sections``), each guarded: a part that fails records its error and the others still run.
  matmul   the bf16 (and fp32) matrix rate of this device (a large random square product): the reference
           every achieved TFLOP/s is compared to.
  encoder  DINOv3 ViT-L/16 (random weights of transformers' DINOv3ViTModel, through wamplan's encoder with
           its ``dtype`` option) on uint8 224 px images; images/s and the time to encode the paper's data.
  train    one optimisation step of the predictor as ``wamplan wm train`` runs it (``window_loss`` + AdamW +
           clipping), paper preset, random features; bf16 = ``torch.autocast`` around the loss (fp32 weights).
  plan     one 32 x 4 search (the paper's CEM by default) in ``LearnedDynamics`` / the naive reference of
           ``benchmarks/planner.py``; bf16 = the predictor cast with ``.to(torch.bfloat16)``;
           compile = ``torch.compile`` of the predictor's rollout, cudagraphs = its "reduce-overhead" mode.
FLOPs are counted with ``FlopCounterMode`` on meta tensors (matmuls and attention; multiply-add = 2).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import torch
from torch.utils.flop_counter import FlopCounterMode

from gpu_report import Row, error_row, machine_info, write_outputs
from wamplan.device import resolve_device
from wamplan.planning.timing import median_time
from wamplan.presets import get_world_model_preset
from wamplan.provenance import provenance

SECTIONS = ("matmul", "encoder", "train", "plan")  # cheap first: a run stopped by its budget keeps them
DTYPES = ("bfloat16", "float32")
MODES = ("eager", "compile", "cudagraphs")
# facebook/dinov3-vitl16-pretrain-lvd1689m's architecture (its weights are not needed to time it)
VITL16 = dict(hidden_size=1024, intermediate_size=4096, num_hidden_layers=24, num_attention_heads=16,
              patch_size=16, num_register_tokens=4)
TINY_VIT = dict(hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=2,
                patch_size=16, num_register_tokens=4)
TINY_PREDICTOR = dict(num_patches=4, enc_dim=32, depth=2, heads=2, head_dim=16, mlp_dim=64, proprio_emb=16,
                      action_emb=16)  # the paper preset's frames, Δ and history, with toy widths
# The paper (§4, appendix B): control steps recorded per source of the augmented world model's 1,600 episodes
PAPER_FRAMES = {"expert": 10_000, "noisy": 50_000, "pink": 42_000, "on_policy": 134_000}
PAPER_EPISODES = 1_600
PAPER_TRAIN_H = 43.0  # predictor training, one RTX 4090
PAPER_PLAN_S = 2.4  # CEM search per chunk, one RTX 5090
GOAL_PLAN_S = 0.2  # issue 42's goal for the paper preset on one H200


@dataclass(frozen=True)
class Settings:
    device: torch.device
    tiny: bool
    dtypes: tuple[str, ...]
    repeats: int
    planner: str
    candidates: int
    iterations: int
    plan_modes: tuple[str, ...]
    naive_modes: tuple[str, ...]
    compile_backend: str
    encoder_batch: int
    train_batch: int
    train_steps: int
    budget_s: float | None  # seconds after which the rows and parts not yet started are skipped (None: no limit)
    started: float = dataclasses.field(default_factory=time.perf_counter)

    def over_budget(self) -> bool:
        return self.budget_s is not None and time.perf_counter() - self.started > self.budget_s


# ------------------------------------------------------------------------------------------------ helpers
def count_flops(fn: Callable[[], Any]) -> int:
    with FlopCounterMode(display=False) as counter:
        fn()
    return int(counter.get_total_flops())


def short(name: str) -> str:
    return {"bfloat16": "bf16", "float32": "fp32"}.get(name, name)


def predictor_config(tiny: bool):
    cfg = get_world_model_preset("paper").predictor
    return dataclasses.replace(cfg, **TINY_PREDICTOR) if tiny else cfg


def guarded(make_row: Callable[[], Row], s: Settings, part: str, dtype: str, variant: str) -> Row:
    """One measured row, or a row that says why there is none (an error, or the budget spent)."""
    if s.over_budget():
        return error_row(part, dtype, variant, "skipped: --budget-s spent", skipped=True)
    try:
        row = make_row()
    except Exception as e:  # a failing variant (a compile error, say) must not cost the other rows
        traceback.print_exc()
        row = error_row(part, dtype, variant, f"{type(e).__name__}: {e}")
    print(f"  {part} {short(dtype)} {variant}: {row.summary()}", flush=True)
    return row


# ------------------------------------------------------------------------------------------------ matmul
def matmul_section(s: Settings) -> dict[str, Any]:
    n, reps = (256, 4) if s.tiny else (8192, 10)
    rows = []
    for name in DTYPES:  # both always: bf16 is the reference, fp32 (TF32 as torch is set) what fp32 rows can reach
        def run(name: str = name) -> Row:
            a, b = (torch.randn(n, n, device=s.device, dtype=getattr(torch, name)) for _ in range(2))  # (n, n)
            c = torch.empty_like(a)  # (n, n)
            sec = median_time(lambda: [torch.mm(a, b, out=c) for _ in range(reps)], s.repeats, s.device, 2) / reps
            return Row("matmul", name, f"{n}x{n}x{n}", sec, "product", flops=2 * n ** 3)
        rows.append(guarded(run, s, "matmul", name, f"{n}^3"))
    return {"rows": rows}


# ------------------------------------------------------------------------------------------------ encoder
def encoder_section(s: Settings) -> dict[str, Any]:
    from transformers import DINOv3ViTConfig, DINOv3ViTModel

    from wamplan.encoders import make_encoder

    size = 64 if s.tiny else 224
    cfg = DINOv3ViTConfig(image_size=size, **(TINY_VIT if s.tiny else VITL16))
    with torch.device("meta"):
        meta = DINOv3ViTModel(cfg).eval()
        flops = count_flops(lambda: meta(pixel_values=torch.zeros(1, 3, size, size)))  # one image
    views = get_world_model_preset("paper").predictor.num_views
    images_total = sum(PAPER_FRAMES.values()) * views
    rows = []
    for name in s.dtypes:
        def run(name: str = name) -> Row:
            torch.manual_seed(0)
            with torch.device(s.device):  # random init straight on the device (ViT-L on a CPU takes long)
                enc = make_encoder("dinov3-vitl16", config=cfg, input_size=size, dtype=name)
            images = torch.randint(0, 256, (s.encoder_batch, size, size, 3), dtype=torch.uint8,
                                   device=s.device)  # (B, H, W, 3)
            sec = median_time(lambda: enc.encode(images), s.repeats, s.device)
            rate = s.encoder_batch / sec  # images/s
            note = (f"{images_total / 1e3:.0f}k images (paper: {sum(PAPER_FRAMES.values()) / 1e3:.0f}k frames of "
                    f"{PAPER_EPISODES:,} episodes x {views} views): {images_total / rate / 3600:.2f} h")
            return Row("encoder", name, f"batch {s.encoder_batch}, {size} px", sec, "batch",
                       throughput=rate, throughput_unit="images/s", flops=flops * s.encoder_batch, projection=note)
        rows.append(guarded(run, s, "encoder", name, f"batch {s.encoder_batch}"))
    return {"rows": rows, "flops_per_image": flops, "images_to_encode": images_total,
            "config": {k: getattr(cfg, k) for k in (*VITL16, "image_size", "_attn_implementation")}}


# ------------------------------------------------------------------------------------------------ train
def random_windows(cfg, batch: int, frames: int, dev: torch.device) -> dict[str, torch.Tensor]:
    """Random features shaped like the trainer's items: z (B, T, V, N, D), q (B, T, P), a (B, T, Δ·A)."""
    return {"z": torch.randn(batch, frames, cfg.num_views, cfg.num_patches, cfg.enc_dim, device=dev),
            "q": torch.randn(batch, frames, cfg.proprio_dim, device=dev),
            "a": torch.rand(batch, frames, cfg.action_block_dim, device=dev) * 2 - 1}


def window_flops(cfg, horizon: int) -> int:
    """Forward + backward FLOPs of one window's K-step rollout (what ``window_loss`` differentiates)."""
    from wamplan.worldmodel.predictor import WorldModelPredictor

    with torch.device("meta"):
        model = WorldModelPredictor(cfg)
        w = random_windows(cfg, 1, cfg.context + horizon, torch.device("meta"))
        h = cfg.context

        def step() -> None:
            z, q = model.rollout(w["z"][:, :h], w["q"][:, :h], w["a"][:, :h - 1], w["a"][:, h - 1:h - 1 + horizon])
            (z.sum() + q.sum()).backward()
        return count_flops(step)


def train_section(s: Settings) -> dict[str, Any]:
    from wamplan.optim import make_adamw, optimizer_step, warmup_cosine
    from wamplan.worldmodel.predictor import WorldModelPredictor
    from wamplan.worldmodel.losses import window_loss

    cfg, tc = predictor_config(s.tiny), get_world_model_preset("paper").train
    flops = window_flops(cfg, tc.horizon)
    windows = sum(PAPER_FRAMES.values()) - PAPER_EPISODES * ((cfg.context + tc.horizon) * cfg.frameskip - 1)

    def run(name: str) -> Row:
        torch.manual_seed(0)
        model = WorldModelPredictor(cfg).to(s.device).train()
        opt = make_adamw(model, tc.lr, tc.weight_decay, tc.betas)
        sched = warmup_cosine(opt, 1, 10 ** 6)  # the schedule's shape does not change the cost of a step
        batch = random_windows(cfg, s.train_batch, cfg.context + tc.horizon, s.device)

        def step() -> None:  # what train_loop.fit runs per batch
            with torch.autocast(s.device.type, dtype=torch.bfloat16, enabled=name == "bfloat16"):
                loss, _ = window_loss(model, batch, tc.horizon, tc.gamma, tc.loss_form)
            optimizer_step(model, opt, sched, loss, tc.grad_clip)
            float(loss.detach())  # fit reads every step's loss
        sec = median_time(step, s.train_steps, s.device, warmup=2)
        rate = s.train_batch / sec  # windows/s
        note = (f"{tc.epochs} epochs x {windows / 1e3:.1f}k windows: {tc.epochs * windows / rate / 3600:.1f} h "
                f"(paper: {PAPER_TRAIN_H:.0f} h, RTX 4090)")
        return Row("train", name, f"batch {s.train_batch}", sec, "step", throughput=rate,
                   throughput_unit="windows/s", flops=flops * s.train_batch, projection=note)

    rows = [guarded(lambda n=name: run(n), s, "train", name, f"batch {s.train_batch}") for name in s.dtypes]
    return {"rows": rows, "flops_per_window": flops, "windows_per_epoch": windows, "epochs": tc.epochs,
            "windows_per_epoch_rule": f"{sum(PAPER_FRAMES.values()):,} frames (paper §4) - {PAPER_EPISODES:,} "
                                      f"episodes x ((H_ctx + K) x Δ - 1) steps a window spans"}


# ------------------------------------------------------------------------------------------------ plan
@contextlib.contextmanager
def compiled(model: torch.nn.Module, method: str, mode: str, backend: str):
    """``model.<method>`` compiled for the duration of the block (an instance attribute over the class's method).

    The predictor's method is compiled, not ``LearnedDynamics.terminal``: that one runs under
    ``torch.inference_mode``, and compiling the decorated method fails on its inference tensors
    (torch 2.13: "Cannot set version_counter for inference tensor")."""
    if mode == "eager":
        yield {}
        return
    if mode == "compile":
        kwargs = {"backend": backend}
    else:  # CUDA graphs: inductor's reduce-overhead, or dynamo's cudagraphs backend when not compiling with inductor
        kwargs = {"mode": "reduce-overhead"} if backend == "inductor" else {"backend": "cudagraphs"}
    torch.compiler.reset()
    setattr(model, method, torch.compile(getattr(model, method), **kwargs))
    try:
        yield kwargs
    finally:
        delattr(model, method)


def plan_variants(s: Settings) -> list[tuple[str, str, str]]:
    """(dtype, path, mode) in the order they run: every eager row first (cheap), then the compiled ones dtype by
    dtype (bf16 first by default), so a run that spends its budget on compiling loses the least telling rows."""
    def wanted(path: str, mode: str) -> bool:
        return mode in (s.plan_modes if path == "cached" else s.naive_modes) and (
            mode != "cudagraphs" or s.device.type == "cuda")
    eager = [(d, path, "eager") for path in ("cached", "naive") for d in s.dtypes if wanted(path, "eager")]
    rest = [(d, path, m) for d in s.dtypes for path in ("cached", "naive") for m in MODES[1:] if wanted(path, m)]
    return eager + rest


def plan_note(sec: float) -> str:
    goal = "met" if sec <= GOAL_PLAN_S else "not met"
    return f"{PAPER_PLAN_S / sec:.3g}x the paper's speed ({PAPER_PLAN_S} s/chunk); goal {GOAL_PLAN_S} s {goal}"


def plan_section(s: Settings) -> dict[str, Any]:
    import planner as bench  # benchmarks/planner.py
    from profile_worldmodel import predictor_stats  # benchmarks/profile_worldmodel.py

    from wamplan.planning import make_planner
    from wamplan.planning.dynamics import LearnedDynamics
    from wamplan.worldmodel.predictor import WorldModelPredictor

    cfg = predictor_config(s.tiny)
    with torch.device("meta"):
        stats = predictor_stats(WorldModelPredictor(cfg), s.candidates, s.iterations)
    flops = {"cached": stats["plan_flops_cached"], "naive": stats["plan_flops_naive"]}
    planner = make_planner(s.planner, bench.planner_settings(s.planner, s.candidates, s.iterations))
    models: dict[str, torch.nn.Module] = {}

    def run(dtype: str, path: str, mode: str) -> Row:
        if dtype not in models:
            torch.manual_seed(0)
            models[dtype] = WorldModelPredictor(cfg).to(s.device, getattr(torch, dtype)).eval()
        model = models[dtype]
        dyn = LearnedDynamics(model) if path == "cached" else bench.NaiveDynamics(model)
        ctx, target = bench.search_inputs(cfg, s.device)
        with compiled(model, "rollout_from_prefix" if path == "cached" else "forward", mode, s.compile_backend) as kw:
            t0 = time.perf_counter()
            sec = bench.time_search(dyn, ctx, target, planner, s.repeats)
            first = time.perf_counter() - t0 - s.repeats * sec  # ~ the warm-up search, compilation included
        return Row("plan", dtype, f"{path}, {mode}", sec, "chunk", throughput=1 / sec, throughput_unit="chunks/s",
                   flops=flops[path], projection=plan_note(sec),
                   extra={"path": path, "mode": mode, "compile": {k: str(v) for k, v in kw.items()},
                          "first_search_s": first})

    rows = [guarded(lambda v=v: run(*v), s, "plan", v[0], f"{v[1]}, {v[2]}") for v in plan_variants(s)]
    measured = {r.extra.get("mode") for r in rows if r.ok}
    not_measured = {m: "CUDA only" if m == "cudagraphs" and s.device.type != "cuda" else "every row failed"
                    for m in s.plan_modes if m not in measured}
    return {"rows": rows, "params": stats["params"], "flops_per_chunk": flops,
            "rollout_steps": stats["rollout_steps_per_chunk"], "planner": s.planner,
            "candidates": s.candidates, "iterations": s.iterations, "modes_not_measured": not_measured}


# ------------------------------------------------------------------------------------------------ main
PARTS: dict[str, Callable[[Settings], dict[str, Any]]] = {
    "matmul": matmul_section, "encoder": encoder_section, "train": train_section, "plan": plan_section}


def run_part(name: str, s: Settings) -> dict[str, Any]:
    """One part's record: its results, or its error (the other parts run on either way)."""
    print(f"[{name}]", flush=True)
    t0 = time.perf_counter()
    if s.over_budget():
        return {"ok": False, "error": "skipped: --budget-s spent", "rows": [], "wall_s": 0.0}
    try:
        out = {"ok": True, **PARTS[name](s)}
    except Exception as e:  # a part that cannot run at all (a missing package, say) leaves the others their turn
        traceback.print_exc()
        out = {"ok": False, "error": f"{type(e).__name__}: {e}", "traceback": traceback.format_exc(), "rows": []}
    out["wall_s"] = time.perf_counter() - t0
    return out


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/gpu", help="directory for gpu_bench.json and gpu_bench.md")
    ap.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"))
    ap.add_argument("--tiny", action="store_true", help="toy sizes (the code path, in seconds on a CPU)")
    ap.add_argument("--sections", nargs="+", default=list(SECTIONS), choices=SECTIONS)
    ap.add_argument("--dtypes", nargs="+", default=list(DTYPES), choices=DTYPES)
    ap.add_argument("--repeats", type=int, default=None, help="timed repeats per row, median reported (5; tiny 2)")
    ap.add_argument("--planner", default="cem", help="planner registry name (cem: the paper's)")
    ap.add_argument("--candidates", type=int, default=32)
    ap.add_argument("--iterations", type=int, default=4)
    ap.add_argument("--plan-modes", nargs="+", default=list(MODES), choices=MODES,
                    help="for the KV-cached search (cudagraphs runs only on CUDA)")
    ap.add_argument("--naive-modes", nargs="+", default=["eager"], choices=MODES,
                    help="for the naive reference (eager: it only measures what the KV cache saves)")
    ap.add_argument("--compile-backend", default="inductor", help="torch.compile backend (aot_eager: quick tests)")
    ap.add_argument("--encoder-batch", type=int, default=None, help="images per encoder call (96; tiny 4)")
    ap.add_argument("--train-batch", type=int, default=None, help="windows per step (the preset's 24; tiny 4)")
    ap.add_argument("--train-steps", type=int, default=None, help="timed training steps (10; tiny 2)")
    ap.add_argument("--budget-s", type=float, default=None, help="skip what is left after this many seconds "
                    "(default 420 at full size, none with --tiny), so the outputs are written in time")
    ap.add_argument("--git-commit", default=None, help="record this commit (where the tree has no .git)")
    return ap.parse_args(argv)


def settings_from(args: argparse.Namespace) -> Settings:
    tiny = args.tiny
    return Settings(
        device=resolve_device(args.device), tiny=tiny, dtypes=tuple(args.dtypes),
        repeats=args.repeats or (2 if tiny else 5), planner=args.planner, candidates=args.candidates,
        iterations=args.iterations, plan_modes=tuple(args.plan_modes), naive_modes=tuple(args.naive_modes),
        compile_backend=args.compile_backend, encoder_batch=args.encoder_batch or (4 if tiny else 96),
        train_batch=args.train_batch or (4 if tiny else get_world_model_preset("paper").train.batch_size),
        train_steps=args.train_steps or (2 if tiny else 10),
        budget_s=args.budget_s if args.budget_s is not None else (None if tiny else 420.0))


def new_report(args: argparse.Namespace, argv: list[str], s: Settings) -> dict[str, Any]:
    """The record's head: command line, commit, machine, settings; the parts fill ``sections``."""
    prov = provenance()
    settings = {k: str(v) if isinstance(v, torch.device) else v for k, v in dataclasses.asdict(s).items()
                if k != "started"}
    return {"schema": "wamplan-gpu-bench/1", "argv": [Path(sys.executable).name, "benchmarks/gpu.py", *argv],
            "git_commit": args.git_commit or prov["git_commit"], "provenance": prov,
            "machine": machine_info(s.device), "settings": settings, "sections": {}}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    s = settings_from(args)
    report = new_report(args, argv, s)
    out = Path(args.out)
    print(f"device {s.device} ({report['machine']['device_name']}), torch {torch.__version__}, "
          f"{'tiny' if s.tiny else 'full'} sizes -> {out}", flush=True)
    for name in (n for n in SECTIONS if n in args.sections):
        report["sections"][name] = run_part(name, s)
        write_outputs(report, out)  # after every part: a run killed at its limit keeps what it measured
    print((out / "gpu_bench.md").read_text())
    failed = [n for n, sec in report["sections"].items() if not sec["ok"] or any(not r.ok for r in sec["rows"])]
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
