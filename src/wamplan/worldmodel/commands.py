"""``wamplan wm encode|train|train-decoder|eval|viz``."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from wamplan.config import add_arguments, from_args
from wamplan.errors import UserError


def _stores(spec: str) -> list[Path]:
    stores = [Path(s) for s in spec.split(",") if s]
    if not stores:
        raise UserError("--data needs at least one episode store directory")
    return stores


def register(sub: argparse._SubParsersAction) -> None:
    from wamplan.worldmodel.config import TrainConfig

    wm = sub.add_parser("wm", help="the world model: encode features, train, evaluate, visualise")
    s = wm.add_subparsers(dest="wm_command", metavar="WM_COMMAND")

    p = s.add_parser("encode", help="encode the stores' images once with the preset's frozen encoder (cached)")
    p.add_argument("--data", required=True, help="episode stores, comma separated")
    p.add_argument("--preset", default="mini", help="mini | paper (which encoder)")
    p.add_argument("--encoder-path", default=None, help="local weights directory for DINOv2/DINOv3 encoders")
    p.add_argument("--device", default="auto")
    p.set_defaults(func=cmd_encode)

    for name, func, what in (("train", cmd_train, "the predictor (paper eq. 2)"),
                             ("train-decoder", cmd_train_decoder, "the decoder (pixels, for pictures only)")):
        p = s.add_parser(name, help=f"train {what}; re-running resumes")
        p.add_argument("--data", required=True, help="episode stores, comma separated")
        p.add_argument("--out", type=Path, required=True, help="run directory (checkpoint/, metrics.jsonl)")
        p.add_argument("--preset", default="mini")
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
    p.add_argument("--camera", default="front", choices=("front", "side", "wrist"))
    p.add_argument("--out", type=Path, default=Path("wm_viz.png"))
    p.set_defaults(func=cmd_viz)


def _encoder(preset, path: str | None, device: str):
    from wamplan.device import resolve_device
    from wamplan.encoders import make_encoder

    kw = dict(preset.encoder_kwargs)
    if path:
        kw["path"] = path
    return make_encoder(preset.encoder, **kw).to(resolve_device(device))


def feature_key(enc) -> str:
    from wamplan.data.features import feature_key as key

    return key(enc.config_dict())


def _encode_all(stores, enc) -> None:
    from tqdm import tqdm

    from wamplan.data.features import encode_store
    from wamplan.data.store import EpisodeStore

    for root in stores:
        n = len(EpisodeStore(root).episode_paths())
        for _ in tqdm(encode_store(root, enc), desc=f"encode {Path(root).name} ({enc.name})", total=n, leave=False):
            pass


def cmd_encode(args: argparse.Namespace) -> int:
    from wamplan.worldmodel.presets import get_preset

    enc = _encoder(get_preset(args.preset), args.encoder_path, args.device)
    _encode_all(_stores(args.data), enc)
    print(f"features cached under <store>/features/{feature_key(enc)}/")
    return 0


def _train_setup(args: argparse.Namespace, decoder: bool):
    from wamplan.worldmodel.presets import get_preset

    preset = get_preset(args.preset)
    base = preset.decoder_train if decoder else preset.train
    train = from_args(type(base), args, base=base)
    enc = _encoder(preset, args.encoder_path, args.device)
    stores = _stores(args.data)
    _encode_all(stores, enc)
    info = enc.config_dict()
    info.pop("path", None)
    return preset, train, enc, stores, info


def cmd_train(args: argparse.Namespace) -> int:
    from wamplan.data.readers import WorldModelWindows
    from wamplan.worldmodel.loop import checkpoint_path
    from wamplan.worldmodel.train import train_predictor

    preset, train, enc, stores, info = _train_setup(args, decoder=False)
    cfg = preset.predictor
    kw = dict(frameskip=cfg.frameskip, history=cfg.context, horizon=train.horizon, features=feature_key(enc),
              window_end=train.window_end,
              val_fraction=args.val_fraction)
    tr, va = WorldModelWindows(stores, split="train", **kw), WorldModelWindows(stores, split="val", **kw)
    print(f"windows: {len(tr)} train, {len(va)} val ({len(tr.episodes)} / {len(va.episodes)} episodes)")
    resume = checkpoint_path(args.out).exists()
    _, metrics = train_predictor(tr, cfg, train, args.out, val_set=va if len(va) else None, device=args.device,
                                 resume=resume, max_steps=args.max_steps, encoder_info=info)
    print(json.dumps(metrics))
    return 0


def cmd_train_decoder(args: argparse.Namespace) -> int:
    from wamplan.data.readers import FeatureFrames
    from wamplan.worldmodel.decoder import train_decoder
    from wamplan.worldmodel.loop import checkpoint_path

    preset, train, enc, stores, info = _train_setup(args, decoder=True)
    tr = FeatureFrames(stores, enc.name, split="train", val_fraction=args.val_fraction)
    va = FeatureFrames(stores, enc.name, split="val", val_fraction=args.val_fraction)
    print(f"frames: {len(tr)} train, {len(va)} val")
    _, metrics = train_decoder(tr, preset.decoder, train, args.out, val_set=va if len(va) else None,
                               device=args.device, resume=checkpoint_path(args.out).exists(),
                               max_steps=args.max_steps, encoder_info=info)
    print(json.dumps(metrics))
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    from wamplan.data.readers import WorldModelWindows
    from wamplan.worldmodel.train import evaluate_predictor, load_world_model

    model, enc = load_world_model(args.ckpt)
    stores = _stores(args.data)
    _encode_all(stores, enc)
    ds = WorldModelWindows(stores, frameskip=model.cfg.frameskip, history=model.cfg.context, horizon=args.horizon,
                           split=args.split, val_fraction=args.val_fraction,
                           features=feature_key(enc))
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


