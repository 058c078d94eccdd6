"""A fine-tuning start (``wm train --init``): the check that a predictor checkpoint can start this run
(:func:`check_init`), and growing one onto the wider tokens of a ``concat`` encoder whose first part it reads
(:func:`grown_dims`, :func:`grow_weights`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from wamplan.checkpoint import checkpoint_dir, read_config
from wamplan.config import to_dict
from wamplan.errors import UserError
from wamplan.worldmodel.config import PredictorConfig, predictor_config
from wamplan.worldmodel.load import KIND
from wamplan.worldmodel.predictor import WorldModelPredictor

def check_init(init: str | Path, cfg: PredictorConfig, encoder_info: dict[str, Any] | None) -> int | None:
    """A fine-tuning start must be a predictor of the same architecture over the same encoder's tokens, or one this
    run grows (:func:`grown_dims`). Returns the start's token size D when it is grown, else None."""
    saved = read_config(checkpoint_dir(init), KIND)
    theirs = to_dict(predictor_config(saved["predictor"]))  # fields added since it was saved: their defaults
    their_encoder = {k: v for k, v in (saved.get("encoder") or {}).items() if k != "path"}
    old_dim = grown_dims(theirs, their_encoder, cfg, encoder_info)
    if old_dim is not None:
        theirs.update(encoder=cfg.encoder, enc_dim=cfg.enc_dim)
        their_encoder = encoder_info or {}
    if theirs != to_dict(cfg):
        diff = {k: (theirs.get(k), v) for k, v in to_dict(cfg).items() if theirs.get(k) != v}
        raise UserError(f"--init {init} is another predictor {diff} (its, this run's); {_init_fix(diff, theirs)}")
    if encoder_info is not None and their_encoder and their_encoder != encoder_info:
        raise UserError(f"--init {init} was trained on encoder {their_encoder}, this run encodes with {encoder_info}; "
                        f"use the encoder it was trained with, or a concat encoder whose first part it is (scale 1)")
    return old_dim


def _init_fix(diff: dict[str, tuple], theirs: dict[str, Any]) -> str:
    """What makes this run the start's architecture: its options, its task's stores, or its encoder."""
    from wamplan.worldmodel.config import ARCHITECTURE_FIELDS

    if {"num_views", "proprio_dim", "action_dim"} & diff.keys():
        return "it was trained on another task's views or actions: fine-tune it on stores of its task"
    if {"encoder", "enc_dim", "num_patches"} & diff.keys():
        return ("it reads other tokens: give this run its encoder (--encoder, --encoder-kwargs), or a concat encoder "
                "whose first part it is, at scale 1")
    flags = [f"--{'' if theirs[k] else 'no-'}{k.replace('_', '-')}" if isinstance(theirs[k], bool) else
             f"--{k.replace('_', '-')} {theirs[k]}" for k in diff if k in ARCHITECTURE_FIELDS]
    rest = sorted(k for k in diff if k not in ARCHITECTURE_FIELDS)
    if flags and not rest:
        return f"fine-tune with its settings ({' '.join(flags)})"
    return "fine-tune with the preset it was trained with (--preset)" + (f", then {' '.join(flags)}" if flags else "")


def grown_dims(theirs: dict[str, Any], their_encoder: dict[str, Any], cfg: PredictorConfig,
               encoder_info: dict[str, Any] | None) -> int | None:
    """The start's token size D when this run's encoder is a ``concat`` whose first part is the start's encoder at
    scale 1 (the start then grows onto the wider tokens: :func:`grow_weights`); None otherwise."""
    if not encoder_info or encoder_info.get("name") != "concat" or not their_encoder:
        return None
    first = {k: v for k, v in encoder_info["parts"][0].items() if k != "path"}
    if first != their_encoder or encoder_info["scales"][0] != 1.0 or theirs["enc_dim"] >= cfg.enc_dim:
        return None
    return int(theirs["enc_dim"])


def grow_weights(weights: dict[str, torch.Tensor], model: WorldModelPredictor, old_dim: int
                 ) -> dict[str, torch.Tensor]:
    """A predictor's weights over D = ``old_dim`` token dims, fitted to ``model``'s wider tokens (D' > D, the old
    dims first): every tensor with one axis D' long where the file's is D long gets zeros for the new dims, inserted
    after the first D entries of that axis (``in_proj``'s input columns [z | q | a] included). The grown model
    predicts the old dims exactly as the start did; the new dims' feature statistics are the caller's to set."""
    own = model.state_dict()
    grow = model.cfg.enc_dim - old_dim
    out = dict(weights)
    for k, v in weights.items():
        if k not in own or own[k].shape == v.shape:
            continue
        axes = [i for i, (a, b) in enumerate(zip(own[k].shape, v.shape)) if a != b]
        if own[k].dim() != v.dim() or len(axes) != 1 or own[k].shape[axes[0]] - v.shape[axes[0]] != grow:
            continue  # left for load_weights to name as a mismatch
        i = axes[0]
        zeros = v.new_zeros(v.shape[:i] + (grow,) + v.shape[i + 1:])
        out[k] = torch.cat([v.narrow(i, 0, old_dim), zeros, v.narrow(i, old_dim, v.shape[i] - old_dim)], dim=i)
    return out
