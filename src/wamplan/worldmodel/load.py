"""Loading a trained world model: the predictor (or a splice of predictors) from its checkpoint directory, and
with it the encoder it was trained on (:func:`load_world_model`), what planning, evaluation and the proxy need of a
world model; training is in :mod:`wamplan.worldmodel.train`.
"""

from __future__ import annotations

from pathlib import Path

import torch

from wamplan.checkpoint import checkpoint_dir, load_weights, read_config, read_meta
from wamplan.device import resolve_device
from wamplan.errors import UserError
from wamplan.worldmodel.predictor import WorldModelPredictor, without_retired
from wamplan.worldmodel.splice import SPLICE_KIND, load_spliced

KIND = "wm-predictor"  # a predictor checkpoint's kind (``checkpoint.read_config``)

def trained_val_fraction(path: str | Path) -> float:
    """The share of episodes a world model's training held out, as its checkpoint records it (0.1 where none)."""
    data = read_meta(checkpoint_dir(path)).get("config", {}).get("data") or {}
    return float(data.get("val_fraction") or 0.1)


def _kind_of(ckpt: Path) -> str:
    """The kind of a world-model checkpoint: a predictor's (``wm-predictor``) or a splice's (``wm-splice``)."""
    return SPLICE_KIND if read_meta(ckpt).get("kind") == SPLICE_KIND else KIND


def load_predictor(path: str | Path, device: str | torch.device = "cpu") -> WorldModelPredictor:
    """A trained predictor (eval mode) from a checkpoint directory (or a training ``out_dir``), with the task and
    cameras it was trained on as ``model.task`` / ``model.cameras`` (a checkpoint that records no task:
    cube-insertion; none records no cameras: the task's). A spliced checkpoint gives its
    :class:`~wamplan.worldmodel.splice.SplicedPredictor`."""
    ckpt = checkpoint_dir(path)
    dev = resolve_device(device) if isinstance(device, str) else device
    if _kind_of(ckpt) == SPLICE_KIND:  # a concat model whose parts other models predict
        return load_spliced(ckpt, dev)
    model = WorldModelPredictor.from_record(read_config(ckpt, KIND))
    load_weights(ckpt, model, adapt=without_retired)  # an older checkpoint's spread head is dropped
    return model.to(dev).eval()


def load_world_model(path: str | Path, device: str | torch.device = "cpu", dtype: str | torch.dtype = "float32"):
    """(predictor, encoder) from a predictor checkpoint; the encoder is rebuilt from the stored config. ``dtype``
    (a torch dtype or its name): the predictor's arithmetic; the encoder stays float32."""
    from wamplan.encoders import make_encoder
    from wamplan.encoders.learned import locate_weights

    ckpt = checkpoint_dir(path)
    info = dict(read_config(ckpt, _kind_of(ckpt)).get("encoder") or {})
    model = load_predictor(path, device).to(getattr(torch, dtype) if isinstance(dtype, str) else dtype)
    name = info.pop("name", model.cfg.encoder)
    enc = make_encoder(name, **locate_weights(name, info, ckpt)).to(next(model.parameters()).device)
    if (enc.num_patches, enc.dim) != (model.cfg.num_patches, model.cfg.enc_dim):
        raise UserError(f"{ckpt}: encoder {name} gives {enc.num_patches} x {enc.dim} tokens, the predictor "
                        f"was trained on {model.cfg.num_patches} x {model.cfg.enc_dim}; "
                        f"use the encoder it was trained with")
    return model, enc
