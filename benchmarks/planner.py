"""Per-chunk planning time of the search in the learned world model (wamplan's default planner, or
``--planner cem`` for the paper's), KV-cached against a straightforward rollout that re-runs the full
predictor over the window at every step, side by side in one run. Random weights (timing only). Prints
one line per preset and the speed-up ratio.

    .venv/bin/python benchmarks/planner.py                       # mini and paper presets, --planner wamplan
    .venv/bin/python benchmarks/planner.py --planner cem         # the paper's CEM (the same 32 x 4 evaluations)
    .venv/bin/python benchmarks/planner.py --presets mini --repeats 10
    .venv/bin/python benchmarks/planner.py --presets paper --candidates 8 --iterations 1 --repeats 1   # CPU
    .venv/bin/python benchmarks/planner.py --presets mini --tasks cube-insertion peg-insertion-side   # per task
    .venv/bin/python benchmarks/planner.py --presets mini --dtypes float32 bfloat16 --compile     # arithmetic
    .venv/bin/python benchmarks/planner.py --presets mini --ckpt runs/wm41/gpu/export             # a trained one's size

With several ``--dtypes`` and/or ``--compile`` (every transformer block through ``torch.compile``, compile time not
counted), each arithmetic is timed on the same model and inputs and also given as a ratio to the first (eager
``--dtypes[0]``); the naive reference is timed for the first only.

With several ``--tasks``, each preset is sized for each task's views, proprio and action (as ``wm train`` does for
a task's stores) and its time is also given as a ratio to the first task's.

With ``--ckpt``, each world-model checkpoint is timed after the presets with its own weights (the time does not
depend on them), and its time also given as a ratio to the first preset's.
"""

from __future__ import annotations

import argparse
import copy
import platform
import statistics

import torch

from wamplan.device import resolve_device
from wamplan.errors import UserError
from wamplan.envs.spec import get_task
from wamplan.planning import PLANNERS, make_cost, make_planner
from wamplan.planning.dynamics import LearnedDynamics, PlanningContext
from wamplan.planning.timing import planner_settings, timed
from wamplan.worldmodel.config import PredictorConfig
from wamplan.worldmodel.predictor import WorldModelPredictor
from wamplan.worldmodel.load import load_predictor
from wamplan.presets import get_world_model_preset as get_preset
from wamplan.worldmodel.stores import predictor_for_task

CHUNK = 16


class NaiveDynamics(LearnedDynamics):
    """The reference: every rollout step re-runs ``forward`` over the whole growing sequence, for every
    candidate, with nothing cached across candidates, steps or iterations."""

    def prepare(self, context):
        self._ctx = context

    @torch.inference_mode()
    def terminal(self, actions):
        c, dev = self._ctx, self.device
        b, length, na = actions.shape
        blocks = actions.to(dev).reshape(b, length // self.frameskip, self.frameskip * na)
        dt = self.dtype
        z, _ = self.model.rollout(c.z[None].to(dev, dt), c.q[None].to(dev, dt), c.a[None].to(dev, dt),
                                  blocks.to(dt), naive=True)
        return z[:, -1].float()  # (B, V, N, D), as LearnedDynamics returns it


def time_search(dyn, ctx, target, planner, repeats: int) -> float:
    """Median seconds of one search over a chunk (its covered actions)."""
    cost = make_cost("patch")
    covered = dyn.covered(CHUNK)
    seed = torch.zeros(covered, dyn.model.cfg.action_dim)  # (L, A)

    def search(i: int) -> None:
        dyn.prepare(ctx)
        planner.plan(seed, lambda c: cost(dyn.terminal(c), target), seed=i)

    return statistics.median([timed(lambda: search(i), dyn.device) for i in range(repeats + 1)][1:])  # 0: warm-up


def search_inputs(cfg: PredictorConfig, dev: torch.device) -> tuple[PlanningContext, torch.Tensor]:
    """A random chunk-boundary history (on the CPU, as the policy hands it over) and target (on ``dev``), float32
    as the encoder gives them whatever the world model's ``dtype`` (the dynamics cast the history)."""
    ctx = PlanningContext(z=torch.randn(cfg.context, cfg.num_views, cfg.num_patches, cfg.enc_dim),
                          q=torch.randn(cfg.context, cfg.proprio_dim),
                          a=torch.rand(cfg.context - 1, cfg.action_block_dim) * 2 - 1)
    target = torch.randn(cfg.num_views, cfg.num_patches, cfg.enc_dim, device=dev)  # (V, N, D)
    return ctx, target


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--presets", nargs="+", default=["mini", "paper"])
    ap.add_argument("--tasks", nargs="+", default=["cube-insertion"], help="registered tasks to size the presets for")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--dtypes", nargs="+", default=["float32"], choices=("float32", "bfloat16"),
                    help="the arithmetic to time side by side (the first is the reference)")
    ap.add_argument("--compile", action="store_true", help="also time each dtype with torch.compile'd blocks")
    ap.add_argument("--planner", default="wamplan", choices=sorted(PLANNERS), help="the search (cem: the paper's)")
    ap.add_argument("--iterations", type=int, default=4, help="search iterations (paper: 4)")
    ap.add_argument("--candidates", type=int, default=32, help="candidates per iteration (paper: 32); fewer "
                    "makes the paper preset feasible on a CPU (the ratio is what compares)")
    ap.add_argument("--ckpt", nargs="+", default=[], help="also time these predictor checkpoints' architectures")
    args = ap.parse_args()
    dev = resolve_device(args.device)
    modes = [(d, c) for d in args.dtypes for c in ((False, True) if args.compile else (False,))]
    print(f"device {dev} ({platform.processor() or platform.machine()}, {torch.get_num_threads()} threads), "
          f"torch {torch.__version__}, {args.planner} {args.candidates} candidates x {args.iterations} "
          f"iterations")
    planner = make_planner(args.planner, planner_settings(args.planner, args.candidates, args.iterations))
    first: dict[str, float] = {}  # preset -> the first task's KV-cached time
    runs = [(n, t, predictor_for_task(get_preset(n).predictor, get_task(t), get_task(t).cameras))
            for n in args.presets for t in args.tasks]
    trained = {path: load_predictor(path) for path in args.ckpt}  # each with its config, task and weights
    runs += [(path, m.task.name, m.cfg) for path, m in trained.items()]
    for name, task, cfg in runs:
        steps = CHUNK // cfg.frameskip
        reference = None  # this preset and task's first arithmetic
        for dtype_name, compiled in modes:
            torch.manual_seed(0)
            dtype = getattr(torch, dtype_name)
            model = (copy.deepcopy(trained[name]) if name in trained else WorldModelPredictor(cfg)).to(dev, dtype).eval()
            ctx, target = search_inputs(cfg, dev)
            if compiled:
                model.compile_blocks()
            fast = time_search(LearnedDynamics(model), ctx, target, planner, args.repeats)
            mode = dtype_name + (" compiled" if compiled else "")
            if reference is not None:
                print(f"[{name} {task} {mode}] KV-cached search {fast:.3f} s/chunk, {fast / reference:.2f}x "
                      f"{modes[0][0]}'s")
                continue
            reference = fast
            slow = time_search(NaiveDynamics(model), ctx, target, planner, args.repeats)
            if name in args.ckpt:  # against the first preset's first task
                versus = f", {fast / first[args.presets[0]]:.2f}x the {args.presets[0]} preset's on {args.tasks[0]}"
            else:
                first.setdefault(name, fast)
                versus = f", {fast / first[name]:.2f}x {args.tasks[0]}'s" if task != args.tasks[0] else ""
            print(f"[{name} {task} {mode}] {model.num_params() / 1e6:.1f} M params, {cfg.num_views}x"
                  f"{cfg.num_patches} tokens/frame, {steps} rollout steps/chunk: KV-cached search {fast:.3f} "
                  f"s/chunk{versus}, naive {slow:.3f} s/chunk, speed-up {slow / fast:.2f}x")


if __name__ == "__main__":
    try:
        main()
    except UserError as e:  # a bad --ckpt, task or preset: one line
        raise SystemExit(f"planner.py: error: {e}") from None
