"""``wamplan wm encode|train|train-decoder|eval|viz|probe|fidelity``."""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

from wamplan.config import ConfigError, Once, add_arguments, as_options, from_args, int_list, one_checkpoint
from wamplan.errors import (UserError, require_dir, require_distinct, require_file, require_paths,
                            require_seeds)
from wamplan.cli.main import add_command, add_group, first_screen, register_command


def write_json(path: Path, obj) -> Path:
    """Write ``obj`` as indented JSON to ``path``, its folder made if missing (after the work: a refused or failed
    run leaves no folder behind)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=1) + "\n")
    return path


def resolve_device(name: str):
    """``--device`` checked before any work (a device this machine lacks is one line); imports torch."""
    from wamplan.device import resolve_device as resolve

    return resolve(name)


def _stores(spec: str) -> list[Path]:
    stores = [Path(s) for s in spec.split(",") if s]
    if not stores:
        raise UserError("--data needs at least one episode store directory")
    require_distinct(stores, "--data", "store")  # read twice, its episodes would weigh double
    return stores


@register_command("wm")
def register(sub: argparse._SubParsersAction) -> None:
    add_group(sub, "wm", _wm_commands, help="the world model: encode features, train, evaluate, visualise")


def _wm_commands(wm: argparse.ArgumentParser) -> None:
    s = wm.add_subparsers(dest="wm_command", metavar="WM_COMMAND")
    add_command(s, "encode", _encode_options,
                help="encode the stores' images once with the preset's frozen encoder (cached)")
    add_command(s, "train", _train_options("train"), help="train the predictor (paper eq. 2); re-running resumes")
    add_command(s, "train-decoder", _train_options("train-decoder"),
                help="train the decoder (pixels, for pictures only); re-running resumes")
    add_command(s, "eval", _eval_options, help="held-out latent errors per horizon against copying the last frame, "
                "and on counterfactual branch groups the sibling statistics per task phase and the planning time per "
                "chunk (a table of those), then every figure as JSON (also to a file with --json); the fixed benchmark "
                "store: scripts/wm_benchmark_store.py")
    add_command(s, "viz", _viz_options, help="ground truth vs autoregressive rollout(s), decoded (paper Figure 4)")
    add_command(s, "probe", _probe_options,
                help="ridge probe from an encoder's frozen tokens to the cube's position (held-out mm)")
    add_command(s, "fidelity", _fidelity_options,
                help="rank agreement of world models with the simulator on the same candidates; with --plan, the "
                     "gate: each model's own plan scored in the simulator")


class OneJSON(Once):
    hint = "one JSON object holds every setting"


ENCODER_KWARGS_HELP = ("the preset's encoder settings, overridden by this JSON object, e.g. '{\"basis\": \"dct\"}' "
                       "(patch-pixels: input_size, patch_size, proj_dim, seed, basis)")
DEVICE_HELP = "torch device: auto, cpu, cuda, cuda:1, mps, ... (default: %(default)s)"


def _encode_options(p: argparse.ArgumentParser) -> None:
    from wamplan.presets import PRESETS

    p.add_argument("--data", required=True, help="episode stores, comma separated")
    p.add_argument("--preset", default="mini", choices=sorted(PRESETS), help="which encoder (wamplan/presets.py)")
    p.add_argument("--encoder", default=None, help="a registered encoder instead of the preset's, e.g. dinov2-vitb14 "
                                                   "(its settings from --encoder-kwargs only)")
    p.add_argument("--encoder-kwargs", default=None, metavar="JSON", action=OneJSON, help=ENCODER_KWARGS_HELP)
    p.add_argument("--encoder-path", default=None, help="local weights directory for DINOv2/DINOv3 encoders")
    p.add_argument("--device", default="auto", help=DEVICE_HELP)
    p.set_defaults(func=cmd_encode)


def _train_options(name: str):
    def build(p: argparse.ArgumentParser) -> None:
        from wamplan.presets import PRESETS
        from wamplan.worldmodel.config import DecoderTrainConfig, TrainConfig, add_architecture_arguments

        p.add_argument("--data", required=True, help="episode stores, comma separated")
        p.add_argument("--out", type=Path, required=True, help="run directory (checkpoint/, metrics.jsonl)")
        p.add_argument("--preset", default="mini", choices=sorted(PRESETS),
                       help="model and training sizes (wamplan/presets.py; default: mini); options below "
                            "override them")
        p.add_argument("--encoder", default=None, help="a registered encoder instead of the preset's, e.g. "
                                                       "dinov2-vitb14 (its settings from --encoder-kwargs only)")
        p.add_argument("--encoder-kwargs", default=None, metavar="JSON", action=OneJSON, help=ENCODER_KWARGS_HELP)
        p.add_argument("--encoder-path", default=None, help="local weights directory for DINOv2/DINOv3 encoders")
        p.add_argument("--val-fraction", type=float, default=0.1,
                       help="fraction of episodes held out for validation (default: 0.1)")
        p.add_argument("--max-steps", type=int, default=None, help="stop after this many steps (resumable)")
        p.add_argument("--device", default="auto", help=DEVICE_HELP)
        if name == "train":
            p.add_argument("--init", type=Path, default=None,
                           help="fine-tune: start from this predictor checkpoint's weights and feature statistics "
                                "(same preset and encoder)")
            add_architecture_arguments(p.add_argument_group("predictor", "the preset's predictor, overridden"),
                                       {k: v.world_model.predictor for k, v in sorted(PRESETS.items())})
        cls, part = (TrainConfig, "train") if name == "train" else (DecoderTrainConfig, "decoder_train")
        add_arguments(p.add_argument_group("training", "the preset's training, overridden"), cls,
                      presets={k: getattr(v.world_model, part) for k, v in sorted(PRESETS.items())})
        first_screen(p, "--preset", "--encoder", "--max-steps", "--device", "--epochs", "--batch-size", "--lr",
                     *(("--init",) if name == "train" else ()))
        p.set_defaults(func=cmd_train if name == "train" else cmd_train_decoder)

    return build


def _eval_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--ckpt", type=Path, required=True, help="predictor checkpoint or run directory")
    p.add_argument("--data", required=True, help="episode stores, comma separated")
    p.add_argument("--horizon", type=int, default=4, help="autoregressive steps to score")
    p.add_argument("--split", default="val", choices=("train", "val", "all"),
                   help="which episodes to score: the held-out ones (val, default), the training ones, or all")
    p.add_argument("--val-fraction", type=float, default=None,
                   help="the held-out fraction (default: the one the model was trained with, as its config.json "
                        "records; 0.1 where it records none)")
    p.add_argument("--json", type=Path, default=None, help="also write the figures to this JSON file")
    p.set_defaults(func=cmd_eval)


def _viz_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--ckpt", type=Path, required=True, help="predictor run directory")
    p.add_argument("--compare", type=Path, default=None, help="a second predictor to show as another row")
    p.add_argument("--decoder", type=Path, required=True, help="decoder run directory")
    p.add_argument("--data", required=True, help="the store holding the episode")
    p.add_argument("--episode", type=int, default=0, help="index in the store's sorted episode list")
    p.add_argument("--start", type=int, default=0, help="step of the first context frame")
    p.add_argument("--steps", type=int, default=12, help="rollout steps h (columns at 0, steps/4, ..., steps)")
    p.add_argument("--camera", default=None, help="which view to show, one of the checkpoint's cameras (default: its "
                                                  "first, e.g. front)")
    p.add_argument("--out", type=Path, default=Path("wm_viz.png"), help="PNG to write (default: wm_viz.png)")
    p.set_defaults(func=cmd_viz)


def _probe_options(p: argparse.ArgumentParser) -> None:
    from wamplan.presets import PRESETS

    p.add_argument("--data", required=True, help="episode stores, comma separated")
    p.add_argument("--preset", default="mini", choices=sorted(PRESETS),
                   help="mini | paper: the preset's encoder (unless --encoder)")
    p.add_argument("--encoder", default=None, help="a registered encoder name, e.g. patch-pixels")
    p.add_argument("--encoder-kwargs", action="append", default=None, metavar="JSON",
                   help='encoder settings as JSON, e.g. \'{"input_size": 64, "patch_size": 8}\'; repeat to '
                        "probe several settings on the same frames")
    p.add_argument("--encoder-path", default=None, help="local weights directory for DINOv2/DINOv3 encoders")
    p.add_argument("--val-fraction", type=float, default=0.25, help="fraction of episodes held out")
    p.add_argument("--folds", type=int, default=4, help="episode folds for choosing the ridge strength")
    p.add_argument("--near-mm", type=float, default=20.0, help="also score frames with the cube this close to the hole")
    p.add_argument("--device", default="auto", help=DEVICE_HELP)
    p.add_argument("--json", type=Path, default=None, help="also write the report(s) to this JSON file")
    p.set_defaults(func=cmd_probe)


def _fidelity_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--wam", required=True, help="WAM checkpoint (e.g. checkpoints/mini/tinywam)")
    p.add_argument("--wm", required=True, help="world-model checkpoints, comma separated; LABEL=PATH to name one")
    p.add_argument("--seeds", required=True, help="episode seeds, e.g. 500-503 or 500,510 (keep test seeds out)")
    p.add_argument("--candidates", type=int, default=32, help="the WAM's chunk + N-1 samples")
    p.add_argument("--sigma", type=float, default=0.10, help="std of the candidates' noise around the WAM's chunk "
                                                             "(default: 0.1, the search's first spread)")
    p.add_argument("--top-k", type=int, default=8, help="score how many of the simulator's k best candidates the "
                                                        "model also ranks in its k best (default: 8)")
    p.add_argument("--boundaries", default="1-4", help="chunk boundaries to score, as chunk indices (1 = step H), "
                                                       "e.g. 1-4 or 1,3,5,7")
    p.add_argument("--sample-seed", type=int, default=0, help="seed of the candidate samples")
    p.add_argument("--camera-size", type=int, default=224, help="rendered image size (as in evaluation)")
    p.add_argument("--cost-view-weights", type=float, nargs="+", default=None,
                   help="per-view weights of the planning cost (front side wrist), as `eval --cost-view-weights`; "
                        "both the model's and the simulator's costs use them")
    p.add_argument("--plan-view-weights", type=float, nargs="+", default=None, metavar="W",
                   help="also score every model ranking (and, with --plan, searching) with these per-view cost weights "
                        "(front side wrist), as LABEL+views; the simulator's yardstick "
                        "keeps --cost-view-weights")
    p.add_argument("--oracle-blend", type=float, default=None, metavar="W",
                   help="also score the first --wm model with its predictions moved W of the way to the simulator's "
                        "(as `eval --oracle-blend`; a diagnostic at the oracle's price), as LABEL@W")
    p.add_argument("--plan", action="store_true",
                   help="also run each model's own search (eval's default planner) at every scored boundary and score "
                        "its plan in the simulator: the true-cost gain planning in that model buys there")
    p.add_argument("--execute", default="", metavar="LABEL",
                   help="run the episodes with this --wm model's plans (condition 7's closed loop, to the episode's "
                        "end) instead of the WAM's chunks, so every model is scored at the states that model reaches")
    p.add_argument("--device", default="auto", help=DEVICE_HELP)
    p.add_argument("--json", type=Path, default=None, help="also write every boundary's scores to this JSON file")
    p.set_defaults(func=cmd_fidelity)


def cmd_encode(args: argparse.Namespace) -> int:
    from wamplan.data.features import feature_key
    from wamplan.presets import get_world_model_preset
    from wamplan.worldmodel.stores import encode_stores, frozen_encoder

    resolve_device(args.device)
    enc = frozen_encoder(*_encoder(args, get_world_model_preset(args.preset)), args.encoder_path, args.device)
    encode_stores(_stores(args.data), enc)
    print(f"features cached under <store>/features/{feature_key(enc.config_dict())}/")
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    from wamplan.presets import get_world_model_preset
    from wamplan.worldmodel.config import TrainConfig, architecture_from_args
    from wamplan.checkpoint import CheckpointError, checkpoint_dir, read_config
    from wamplan.train_loop import check_run_dir
    from wamplan.train_log import require_backends
    from wamplan.worldmodel.stores import train_predictor_on_stores
    from wamplan.worldmodel.load import KIND

    require_dir(args.out)
    check_run_dir(args.out, "a world-model training run")  # before the stores are encoded, which may take long
    if args.init is not None:
        require_paths([str(args.init)], "--init", "pass a world-model checkpoint or run directory to fine-tune")
        try:
            read_config(checkpoint_dir(args.init), KIND)
        except CheckpointError as e:
            raise UserError(f"--init: {e}") from None
    resolve_device(args.device)
    p = get_world_model_preset(args.preset)
    encoder, encoder_kwargs = _encoder(args, p)
    architecture, train = architecture_from_args(args, p.predictor), from_args(TrainConfig, args, p.train)
    require_backends(train.log)  # before the stores are encoded
    stores = _stores(args.data)
    metrics = train_predictor_on_stores(stores, args.out, architecture, train,
                                        encoder=encoder, encoder_kwargs=encoder_kwargs,
                                        encoder_path=args.encoder_path, val_fraction=args.val_fraction,
                                        device=args.device, max_steps=args.max_steps, init=args.init)
    print(json.dumps(metrics))
    return 0


def cmd_train_decoder(args: argparse.Namespace) -> int:
    from wamplan.presets import get_world_model_preset
    from wamplan.train_log import require_backends
    from wamplan.worldmodel.config import DecoderTrainConfig
    from wamplan.worldmodel.stores import train_decoder_on_stores

    require_dir(args.out)
    resolve_device(args.device)
    p = get_world_model_preset(args.preset)
    encoder, encoder_kwargs = _encoder(args, p)
    train = from_args(DecoderTrainConfig, args, p.decoder_train)
    require_backends(train.log)  # before the stores are encoded
    metrics = train_decoder_on_stores(_stores(args.data), args.out, p.decoder, train,
                                      encoder=encoder, encoder_kwargs=encoder_kwargs,
                                      encoder_path=args.encoder_path,
                                      val_fraction=args.val_fraction, device=args.device, max_steps=args.max_steps)
    print(json.dumps(metrics))
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    from wamplan.data.features import feature_key
    from wamplan.data.readers import BranchGroups, WorldModelWindows
    from wamplan.data.store import stores_task
    from wamplan.worldmodel.stores import encode_stores
    from wamplan.worldmodel.load import load_world_model, trained_val_fraction
    from wamplan.worldmodel.train import evaluate_predictor

    require_file(args.json, "--json")
    if args.horizon < 1:
        raise UserError(f"--horizon {args.horizon}: score at least one step ahead (e.g. --horizon 4)")
    model, enc = load_world_model(args.ckpt)
    if args.val_fraction is None:
        args.val_fraction = trained_val_fraction(args.ckpt)
    stores = _stores(args.data)
    task, cameras = stores_task(stores)
    if task.name != model.task.name or cameras != (model.cameras or cameras):
        raise UserError(f"--data holds task '{task.name}' (cameras {list(cameras)}) but {args.ckpt} was trained on "
                        f"task '{model.task.name}' (cameras {list(model.cameras)}); score it on stores of its task")
    encode_stores(stores, enc)
    ds = WorldModelWindows(stores, frameskip=model.cfg.frameskip, history=model.cfg.context, horizon=args.horizon,
                           split=args.split, val_fraction=args.val_fraction,
                           features=feature_key(enc.config_dict()))
    if len(ds) == 0:
        raise UserError(f"no {args.split} windows of {model.cfg.context}+{args.horizon} frames in {args.data}")
    m = evaluate_predictor(model, ds, args.horizon, 0.95)
    groups = BranchGroups(stores, model.cfg.frameskip, model.cfg.context, args.horizon, split=args.split,
                          val_fraction=args.val_fraction, features=feature_key(enc.config_dict()))
    if len(groups):  # the data has counterfactual branches: how well the model tells sibling chunks apart
        report = _phase_report(model, groups, args)
        pooled = report["phases"]["all"]  # train.evaluate_siblings's figures
        m.update({k: pooled[k] for k in (f"sib_mse_h{args.horizon}", f"sib_rel_h{args.horizon}",
                                         f"sib_gain_h{args.horizon}")}, sibling_groups=pooled["groups"])
        m.update(report)
    out = dict(ckpt=str(args.ckpt), data=args.data, split=args.split, val_fraction=args.val_fraction,
               windows=len(ds), horizon=args.horizon, frameskip=model.cfg.frameskip, **m)
    print(json.dumps(out, indent=1))
    if args.json:
        write_json(args.json, out)
    return 0


def _phase_report(model, groups, args: argparse.Namespace) -> dict:
    """Print the benchmark table (worldmodel/benchmark.py) and return its figures for the JSON."""
    import torch

    from wamplan.planning.dynamics import PlanningContext
    from wamplan.planning.timing import plan_seconds
    from wamplan.worldmodel.benchmark import ALL, PHASE_TASK, PHASES, context_of, format_phase_table, phase_table

    labels = None  # the phases of the groups (their task's stage flags)
    if model.task.name != PHASE_TASK:
        print(f"note: the phases ({', '.join(PHASES)}) are defined for task {PHASE_TASK}, not {model.task.name}: "
              f"the table has the '{ALL}' row only")
        labels = [ALL] * len(groups)
    table = phase_table(model, groups, args.horizon, phases=labels)
    z, q, a, target = context_of(groups, model.cfg.context)
    secs = plan_seconds(model, PlanningContext(z=z, q=q, a=a), target)
    print(format_phase_table(table, args.horizon, secs, title=f"{args.ckpt} on {args.data} ({args.split}; "
                             f"{torch.get_num_threads()} threads)"))
    return dict(phases=table, plan_s_per_chunk=secs)


def cmd_viz(args: argparse.Namespace) -> int:
    from wamplan.worldmodel.viz import rollout_figure

    require_file(args.out, "--out")
    rollout_figure(args.ckpt, args.decoder, args.data, episode=args.episode, start=args.start, steps=args.steps,
                   camera=args.camera, out=args.out, compare=args.compare)
    print(f"wrote {args.out}")
    return 0




def _encoder(args: argparse.Namespace, preset) -> tuple[str, dict]:
    """The encoder a command uses: ``--encoder`` with only ``--encoder-kwargs``' settings, else the preset's
    encoder with its settings overridden by them."""
    if args.encoder:
        return args.encoder, _encoder_kwargs({}, args.encoder_kwargs)
    return preset.encoder, _encoder_kwargs(preset.encoder_kwargs, args.encoder_kwargs)


def _encoder_kwargs(base: dict, spec: str | None) -> dict:
    """``base`` (a preset's encoder settings) overridden by ``spec``, a JSON object from --encoder-kwargs."""
    kw = dict(base)
    if spec is not None:
        try:
            extra = json.loads(spec)
        except json.JSONDecodeError as e:
            raise UserError(f"--encoder-kwargs {spec!r} is not JSON ({e}); write e.g. '{{\"patch_size\": 8}}'")
        if not isinstance(extra, dict):
            raise UserError(f"--encoder-kwargs {spec!r} must be a JSON object, e.g. '{{\"patch_size\": 8}}'")
        for key, where in (("name", "--preset (or --encoder where there is one)"), ("path", "--encoder-path")):
            if key in extra:
                raise UserError(f"--encoder-kwargs cannot set {key!r}: use {where}")
        kw.update(extra)
    return kw


def _probe_encoders(args: argparse.Namespace) -> list:
    from wamplan.presets import get_world_model_preset
    from wamplan.worldmodel.stores import frozen_encoder

    preset = get_world_model_preset(args.preset)
    name = args.encoder or preset.encoder
    base = {} if args.encoder else preset.encoder_kwargs  # the preset's settings, overridden by the JSON
    return [frozen_encoder(name, _encoder_kwargs(base, spec), args.encoder_path, args.device)
            for spec in args.encoder_kwargs or [None]]


def cmd_probe(args: argparse.Namespace) -> int:
    from wamplan.encoders.probe import ProbeConfig, format_probe, probe_stores

    require_file(args.json, "--json")
    resolve_device(args.device)
    cfg = ProbeConfig(val_fraction=args.val_fraction, folds=args.folds, near_mm=args.near_mm)
    reports = probe_stores(_stores(args.data), _probe_encoders(args), cfg, progress=True)
    for rep in reports:
        print(format_probe(rep))
    if args.json:
        write_json(args.json, reports if len(reports) > 1 else reports[0])
        print(f"wrote {args.json}")
    return 0


def _view_cost(flag: str, weights: list[float] | None):
    """The patch cost with ``weights`` per camera (None: uniform, the paper's); CostConfig's refusal of weights
    below 0 or summing to 0 as one line naming ``flag``."""
    from wamplan.config import ConfigError
    from wamplan.planning.costs import CostConfig, build_cost

    try:
        return build_cost(CostConfig(view_weights=tuple(weights or ())))
    except ConfigError:
        raise UserError(f"{flag} {' '.join(f'{w:g}' for w in weights or ())}: give weights >= 0 with a positive sum, "
                        f"one per camera (e.g. 1 1 0.5)") from None


def cmd_fidelity(args: argparse.Namespace) -> int:
    from wamplan.envs.config import EnvConfig
    from wamplan.envs.core import TaskEnv
    from wamplan.planning.dynamics import LearnedDynamics
    from wamplan.evaluation.fidelity import FidelityConfig, Scored, format_fidelity, run_fidelity
    from wamplan.wam import load_wam
    from wamplan.worldmodel.load import load_world_model

    flags = dict(num_candidates="--candidates", sigma="--sigma", top_k="--top-k",
                 boundaries="--boundaries", seed="--sample-seed")
    try:
        cfg = FidelityConfig(num_candidates=args.candidates, sigma=args.sigma, top_k=args.top_k,
                             boundaries=tuple(int_list(args.boundaries, "--boundaries", example="2-8 or 2,5,8")),
                             seed=args.sample_seed, plan=args.plan, execute=args.execute)
    except ConfigError as e:  # named by the options, as from_args names them
        raise UserError(as_options(str(e), "FidelityConfig", flags)) from None
    seeds = int_list(args.seeds, "--seeds")
    for seed in (min(seeds), max(seeds)):
        require_seeds(seed, flag="--seeds")
    require_file(args.json, "--json")
    resolve_device(args.device)
    specs = []
    for spec in (s for s in args.wm.split(",") if s):
        label, _, path = spec.rpartition("=")
        path = one_checkpoint(path, "--wm")  # A+B (an ensemble, which left the core): one line
        specs.append((label or Path(path).name, path))
    viewed = "{}+views".format  # twins
    labels = [lab for lab, _ in specs]
    if args.plan_view_weights is not None:
        labels += [viewed(lab) for lab, _ in specs]
    cost, plan_cost = (_view_cost(flag, weights) for flag, weights in (
        ("--cost-view-weights", args.cost_view_weights), ("--plan-view-weights", args.plan_view_weights)))
    blend = f"{labels[0]}@{args.oracle_blend:g}" if args.oracle_blend is not None and labels else None
    if blend:
        if not 0 < args.oracle_blend <= 1:
            raise UserError(f"--oracle-blend {args.oracle_blend:g} is outside (0, 1]; 0.25 removes a quarter of the "
                            f"model's error on every candidate, 1 is the simulator")
        labels.append(blend)
    if args.execute and args.execute not in labels:
        raise UserError(f"--execute {args.execute} names no --wm model; pass one of the labels {', '.join(labels)} "
                        f"(name a model with LABEL=PATH)")
    dup = sorted(lab for lab, n in Counter(labels).items() if n > 1)
    if dup:
        raise UserError(f"--wm labels must differ (twins are LABEL+views, LABEL@W): "
                        f"{', '.join(dup)} "
                        f"appears twice; name each model, e.g. --wm shipped=DIR,new=DIR")
    models, tasks = [], {}  # world-model path -> the task it was trained on
    for label, path in specs:
        require_paths([path], "--wm", "pass a world-model checkpoint directory")
        predictor, encoder = load_world_model(path, device=args.device)
        tasks[path] = predictor.task.name
        models.append(Scored(label, LearnedDynamics(predictor), encoder))
    if args.plan_view_weights is not None:  # each model's twin, sharing its dynamics, planning with those weights
        plain = {m.label: m for m in models}
        models += [Scored(viewed(label), plain[label].dynamics, plain[label].encoder, cost=plan_cost)
                   for label, _ in specs]
    wam = load_wam(args.wam, device=args.device)
    cams = list(wam.task.cameras)
    for flag, weights in (("--cost-view-weights", args.cost_view_weights), ("--plan-view-weights",
                                                                            args.plan_view_weights)):
        if weights and len(weights) != len(cams):
            raise UserError(f"{flag} has {len(weights)} weights for the task's {len(cams)} cameras {cams}; give "
                            f"one weight per camera")
    for path, task in tasks.items():
        if task != wam.task.name:
            raise UserError(f"--wm {path} was trained on task '{task}' but --wam {args.wam} acts in task "
                            f"'{wam.task.name}'; score world models of the WAM's task")
    env_cfg = EnvConfig(task=wam.task.name, camera_size=args.camera_size)
    last = (env_cfg.episode_steps - 1) // wam.chunk_length  # the last chunk boundary inside an episode
    if max(cfg.boundaries) > last:
        raise UserError(f"--boundaries {args.boundaries} reaches chunk {max(cfg.boundaries)}, past the episode: task "
                        f"'{wam.task.name}' ends at step {env_cfg.episode_steps}, so its last boundary is chunk {last} "
                        f"(step {last * wam.chunk_length}; a chunk is {wam.chunk_length} steps)")
    env = TaskEnv(env_cfg)
    if blend:  # the first model's dynamics shared, its prediction moved toward the simulator's with its encoder
        from wamplan.planning.dynamics import BlendedDynamics, SimulatorDynamics

        first = models[0]
        models.append(Scored(blend, BlendedDynamics(first.dynamics, SimulatorDynamics(env, first.encoder),
                                                    args.oracle_blend), first.encoder))

    def progress(seed, result, records):
        mine = [r for r in records if r["seed"] == seed]
        sp = {m.label: [round(r["models"][m.label]["spearman"], 2) for r in mine] for m in models}
        run = f" ({args.execute}'s plans: {result.outcome})" if args.execute else ""
        print(f"seed {seed}: {len(mine)} boundaries, {result.length} steps{run}, Spearman {sp}", flush=True)

    try:
        out = run_fidelity(env, wam, models, seeds, cfg, progress=progress, cost=cost)
    finally:
        env.close()
    print(format_fidelity(out["summary"], cfg.top_k))
    if args.execute:
        won = sum(e["success"] for e in out["episodes"])
        print(f"{args.execute}'s closed loop: {won}/{len(out['episodes'])} episodes succeeded")
    if args.json:
        from wamplan.config import to_dict

        out.update(wam=args.wam, wm=args.wm, seeds=seeds, config=to_dict(cfg), camera_size=args.camera_size)
        write_json(args.json, out)
        print(f"wrote {args.json}")
    return 0
