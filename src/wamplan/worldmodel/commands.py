"""``wamplan wm encode|train|train-decoder|eval|viz``."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from wamplan.config import add_arguments, from_args
from wamplan.envs.contract import CAMERAS
from wamplan.errors import UserError
from wamplan.registry import register_command
from wamplan.worldmodel.config import TrainConfig


def _stores(spec: str) -> list[Path]:
    stores = [Path(s) for s in spec.split(",") if s]
    if not stores:
        raise UserError("--data needs at least one episode store directory")
    return stores


@register_command("wm")
def register(sub: argparse._SubParsersAction) -> None:
    from wamplan.presets import PRESETS

    wm = sub.add_parser("wm", help="the world model: encode features, train, evaluate, visualise")
    s = wm.add_subparsers(dest="wm_command", metavar="WM_COMMAND")

    p = s.add_parser("encode", help="encode the stores' images once with the preset's frozen encoder (cached)")
    p.add_argument("--data", required=True, help="episode stores, comma separated")
    p.add_argument("--preset", default="mini", choices=sorted(PRESETS), help="which encoder (wamplan/presets.py)")
    p.add_argument("--encoder-path", default=None, help="local weights directory for DINOv2/DINOv3 encoders")
    p.add_argument("--device", default="auto")
    p.set_defaults(func=cmd_encode)

    for name, func, what in (("train", cmd_train, "the predictor (paper eq. 2)"),
                             ("train-decoder", cmd_train_decoder, "the decoder (pixels, for pictures only)")):
        p = s.add_parser(name, help=f"train {what}; re-running resumes")
        p.add_argument("--data", required=True, help="episode stores, comma separated")
        p.add_argument("--out", type=Path, required=True, help="run directory (checkpoint/, metrics.jsonl)")
        p.add_argument("--preset", default="mini", choices=sorted(PRESETS),
                       help="model and training sizes (wamplan/presets.py); options below override them")
        p.add_argument("--encoder-path", default=None)
        p.add_argument("--val-fraction", type=float, default=0.1)
        p.add_argument("--max-steps", type=int, default=None, help="stop after this many steps (resumable)")
        p.add_argument("--device", default="auto")
        add_arguments(p, TrainConfig)
        p.set_defaults(func=func)

    p = s.add_parser("eval", help="held-out latent errors per horizon against copying the last frame (JSON)")
    p.add_argument("--ckpt", type=Path, required=True)
    p.add_argument("--data", required=True)
    p.add_argument("--horizon", type=int, default=4, help="autoregressive steps to score")
    p.add_argument("--split", default="val", choices=("train", "val", "all"))
    p.add_argument("--val-fraction", type=float, default=0.1)
    p.add_argument("--json", type=Path, default=None)
    p.set_defaults(func=cmd_eval)

    p = s.add_parser("viz", help="ground truth vs autoregressive rollout(s), decoded (paper Figure 4)")
    p.add_argument("--ckpt", type=Path, required=True, help="predictor run directory")
    p.add_argument("--compare", type=Path, default=None, help="a second predictor to show as another row")
    p.add_argument("--decoder", type=Path, required=True, help="decoder run directory")
    p.add_argument("--data", required=True, help="the store holding the episode")
    p.add_argument("--episode", type=int, default=0, help="index in the store's sorted episode list")
    p.add_argument("--start", type=int, default=0, help="step of the first context frame")
    p.add_argument("--steps", type=int, default=12, help="rollout steps h (columns at 0, steps/4, ..., steps)")
    p.add_argument("--camera", default="front", choices=CAMERAS)
    p.add_argument("--out", type=Path, default=Path("wm_viz.png"))
    p.set_defaults(func=cmd_viz)


def cmd_encode(args: argparse.Namespace) -> int:
    from wamplan.data.features import feature_key
    from wamplan.presets import get_world_model_preset
    from wamplan.worldmodel.stores import encode_stores, frozen_encoder

    preset = get_world_model_preset(args.preset)
    enc = frozen_encoder(preset.encoder, preset.encoder_kwargs, args.encoder_path, args.device)
    encode_stores(_stores(args.data), enc)
    print(f"features cached under <store>/features/{feature_key(enc.config_dict())}/")
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    from wamplan.presets import get_world_model_preset
    from wamplan.worldmodel.stores import train_predictor_on_stores

    p = get_world_model_preset(args.preset)
    metrics = train_predictor_on_stores(_stores(args.data), args.out, p.predictor, from_args(TrainConfig, args, p.train),
                                        encoder=p.encoder, encoder_kwargs=p.encoder_kwargs,
                                        encoder_path=args.encoder_path, val_fraction=args.val_fraction,
                                        device=args.device, max_steps=args.max_steps)
    print(json.dumps(metrics))
    return 0


def cmd_train_decoder(args: argparse.Namespace) -> int:
    from wamplan.presets import get_world_model_preset
    from wamplan.worldmodel.stores import train_decoder_on_stores

    p = get_world_model_preset(args.preset)
    metrics = train_decoder_on_stores(_stores(args.data), args.out, p.decoder,
                                      from_args(TrainConfig, args, p.decoder_train), encoder=p.encoder,
                                      encoder_kwargs=p.encoder_kwargs, encoder_path=args.encoder_path,
                                      val_fraction=args.val_fraction, device=args.device, max_steps=args.max_steps)
    print(json.dumps(metrics))
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    from wamplan.data.features import feature_key
    from wamplan.data.readers import WorldModelWindows
    from wamplan.worldmodel.stores import encode_stores
    from wamplan.worldmodel.train import evaluate_predictor, load_world_model

    model, enc = load_world_model(args.ckpt)
    stores = _stores(args.data)
    encode_stores(stores, enc)
    ds = WorldModelWindows(stores, frameskip=model.cfg.frameskip, history=model.cfg.context, horizon=args.horizon,
                           split=args.split, val_fraction=args.val_fraction,
                           features=feature_key(enc.config_dict()))
    if len(ds) == 0:
        raise UserError(f"no {args.split} windows of {model.cfg.context}+{args.horizon} frames in {args.data}")
    m = evaluate_predictor(model, ds, args.horizon, 0.95)
    out = dict(ckpt=str(args.ckpt), data=args.data, split=args.split, windows=len(ds), horizon=args.horizon,
               frameskip=model.cfg.frameskip, **m)
    print(json.dumps(out, indent=1))
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


def cmd_viz(args: argparse.Namespace) -> int:
    from wamplan.worldmodel.viz import rollout_figure

    rollout_figure(args.ckpt, args.decoder, args.data, episode=args.episode, start=args.start, steps=args.steps,
                   camera=args.camera, out=args.out, compare=args.compare)
    print(f"wrote {args.out}")
    return 0


