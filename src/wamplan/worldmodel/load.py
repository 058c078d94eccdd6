"""Loading a trained world model: the predictor from its checkpoint directory, and with it the encoder it was
trained on (:func:`load_world_model`), what planning, evaluation and the proxy need of a world model; training is
in :mod:`wamplan.worldmodel.train`.
"""

from __future__ import annotations

from pathlib import Path

import torch

from wamplan.checkpoint import checkpoint_dir, load_weights, read_config, read_meta
from wamplan.device import resolve_device
from wamplan.errors import UserError
from wamplan.worldmodel.predictor import WorldModelPredictor, without_retired

KIND = "wm-predictor"  # a predictor checkpoint's kind (``checkpoint.read_config``)
# World-model checkpoint kinds that left the core (no measured gain; their record is in the lab's table): kind -> what
# it was, and the last commit that loads it.
RETIRED_KINDS = {"wm-splice": ("a spliced model (worldmodel.splice)", "9c6eb5d")}

def trained_val_fraction(path: str | Path) -> float:
    """The share of episodes a world model's training held out, as its checkpoint records it (0.1 where none)."""
    data = read_meta(checkpoint_dir(path)).get("config", {}).get("data") or {}
    return float(data.get("val_fraction") or 0.1)


def load_predictor(path: str | Path, device: str | torch.device = "cpu") -> WorldModelPredictor:
    """A trained predictor (eval mode) from a checkpoint directory (or a training ``out_dir``), with the task and
    cameras it was trained on as ``model.task`` / ``model.cameras`` (a checkpoint that records no task:
    cube-insertion; none records no cameras: the task's). One of :data:`RETIRED_KINDS` is refused in one line."""
    ckpt = checkpoint_dir(path)
    dev = resolve_device(device) if isinstance(device, str) else device
    kind = read_meta(ckpt).get("kind")
    if kind in RETIRED_KINDS:
        what, last = RETIRED_KINDS[kind]
        raise UserError(f"{ckpt} is {what}, which left wamplan (it measured no gain: lab/README.md); it loads at "
                        f"commit {last} or earlier")
    model = WorldModelPredictor.from_record(read_config(ckpt, KIND))
    load_weights(ckpt, model, adapt=without_retired)  # an older checkpoint's spread or state head is dropped
    return model.to(dev).eval()


def load_world_model(path: str | Path, device: str | torch.device = "cpu", dtype: str | torch.dtype = "float32"):
    """(predictor, encoder) from a predictor checkpoint; the encoder is rebuilt from the stored config. ``dtype``
    (a torch dtype or its name): the predictor's arithmetic; the encoder stays float32."""
    from wamplan.encoders import make_encoder

    ckpt = checkpoint_dir(path)
    model = load_predictor(path, device).to(getattr(torch, dtype) if isinstance(dtype, str) else dtype)
    info = dict(read_config(ckpt, KIND).get("encoder") or {})
    name = info.pop("name", model.cfg.encoder)
    enc = make_encoder(name, **info).to(next(model.parameters()).device)
    if (enc.num_patches, enc.dim) != (model.cfg.num_patches, model.cfg.enc_dim):
        raise UserError(f"{ckpt}: encoder {name} gives {enc.num_patches} x {enc.dim} tokens, the predictor "
                        f"was trained on {model.cfg.num_patches} x {model.cfg.enc_dim}; "
                        f"use the encoder it was trained with")
    return model, enc
