"""A fine-tuning start (``wm train --init``): the check that a predictor checkpoint can start this run
(:func:`check_init`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from wamplan.checkpoint import checkpoint_dir, read_config
from wamplan.config import to_dict
from wamplan.errors import UserError
from wamplan.worldmodel.config import PredictorConfig, predictor_config
from wamplan.worldmodel.load import KIND


def check_init(init: str | Path, cfg: PredictorConfig, encoder_info: dict[str, Any] | None) -> None:
    """A fine-tuning start must be a predictor of the same architecture over the same encoder's tokens."""
    saved = read_config(checkpoint_dir(init), KIND)
    theirs = to_dict(predictor_config(saved["predictor"]))  # fields added since it was saved: their defaults
    their_encoder = {k: v for k, v in (saved.get("encoder") or {}).items() if k != "path"}
    if theirs != to_dict(cfg):
        diff = {k: (theirs.get(k), v) for k, v in to_dict(cfg).items() if theirs.get(k) != v}
        raise UserError(f"--init {init} is another predictor {diff} (its, this run's); {_init_fix(diff, theirs)}")
    if encoder_info is not None and their_encoder and their_encoder != encoder_info:
        raise UserError(f"--init {init} was trained on encoder {their_encoder}, this run encodes with {encoder_info}; "
                        f"use the encoder it was trained with")


def _init_fix(diff: dict[str, tuple], theirs: dict[str, Any]) -> str:
    """What makes this run the start's architecture: its options, its task's stores, or its encoder."""
    from wamplan.worldmodel.config import ARCHITECTURE_FIELDS

    if {"num_views", "proprio_dim", "action_dim"} & diff.keys():
        return "it was trained on another task's views or actions: fine-tune it on stores of its task"
    if {"encoder", "enc_dim", "num_patches"} & diff.keys():
        return "it reads other tokens: give this run its encoder (--encoder, --encoder-kwargs)"
    flags = [f"--{'' if theirs[k] else 'no-'}{k.replace('_', '-')}" if isinstance(theirs[k], bool) else
             f"--{k.replace('_', '-')} {theirs[k]}" for k in diff if k in ARCHITECTURE_FIELDS]
    rest = sorted(k for k in diff if k not in ARCHITECTURE_FIELDS)
    if flags and not rest:
        return f"fine-tune with its settings ({' '.join(flags)})"
    return "fine-tune with the preset it was trained with (--preset)" + (f", then {' '.join(flags)}" if flags else "")

