"""A ``concat`` world model with its parts weighed anew in the planning cost, exactly and without training.

The predictor normalises its input tokens per dim by the feature statistics it keeps (``z_mean``, ``z_std``, (D,))
and scales its outputs back. Multiplying one part's tokens by c and that part's statistics by c leaves every
normalised number as it was and multiplies the part's predictions by c. So a model trained on ``concat`` scales s
is, exactly, a model of the same encoder at scales s' (its statistics times s'/s per part), and the planning cost,
a plain mean of squared differences over dims, then weighs part i (s'_i / s_i)² as much as before.

    from wamplan.worldmodel.reweigh import reweigh_parts
    reweigh_parts("runs/concat/checkpoint", [1, 1.0], "runs/concat_w1")  # the learned part at scale 1
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import torch

from wamplan.checkpoint import checkpoint_dir, read_config, save_checkpoint
from wamplan.errors import UserError
from wamplan.worldmodel.train import KIND, load_world_model


def reweigh_parts(src: str | Path, scales: Sequence[float], dst: str | Path) -> Path:
    """Write to ``dst`` the predictor of ``src`` (a run or checkpoint on a ``concat`` encoder) for the same encoder
    at ``scales`` (one positive number per part): its feature statistics scaled per part by new / old scale, its
    encoder record given the new scales. Returns the checkpoint directory. A model on another encoder, scales that
    are not one positive number per part, or a ``dst`` that exists, is refused in one line."""
    ckpt = checkpoint_dir(src)
    config = read_config(ckpt, KIND)
    encoder = dict(config.get("encoder") or {})
    if encoder.get("name") != "concat":
        raise UserError(f"{src} was trained on encoder {encoder.get('name')!r}; only a concat model's parts can be "
                        f"weighed anew (wm train --encoder concat)")
    old = [float(s) for s in encoder["scales"]]
    new = list(scales)
    if len(new) != len(old) or not all(isinstance(s, (int, float)) and not isinstance(s, bool) and
                                       math.isfinite(s) and s > 0 for s in new):
        raise UserError(f"scales must be one positive number per part ({len(old)}, now {old}), got {new}")
    if Path(dst).exists():
        raise UserError(f"{dst} exists; give a new directory for the reweighed model (nothing is overwritten)")
    model, enc = load_world_model(ckpt)
    factor = torch.cat([torch.full((part.dim,), s / o) for part, s, o in zip(enc.parts, new, old)])  # (D,)
    with torch.no_grad():  # the buffers themselves: set_feature_stats' floor on the std would break exactness
        model.z_mean.mul_(factor)
        model.z_std.mul_(factor)
    encoder["scales"] = [float(s) for s in new]
    config = {**config, "encoder": encoder, "reweighed": {"from": str(ckpt), "scales": old}}
    return save_checkpoint(dst, model, config, kind=KIND)
