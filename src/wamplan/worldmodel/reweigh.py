"""A ``concat`` world model's parts weighed anew in the planning cost, or predicted by other models; no training.

The predictor normalises its input tokens per dim by the feature statistics it keeps (``z_mean``, ``z_std``, (D,))
and scales its outputs back. Multiplying one part's tokens by c and that part's statistics by c leaves every
normalised number as it was and multiplies the part's predictions by c. So a model trained on ``concat`` scales s
is, exactly, a model of the same encoder at scales s' (its statistics times s'/s per part), and the planning cost,
a plain mean of squared differences over dims, then weighs part i (s'_i / s_i)² as much as before.

    from wamplan.worldmodel.reweigh import reweigh_parts
    reweigh_parts("runs/concat/checkpoint", [1, 1.0], "runs/concat_w1")  # the learned part at scale 1

:func:`splice_parts` writes a spliced model (``worldmodel.splice``): the concat model with part i's predictions taken
from a model trained on that part's encoder alone, e.g. the shipped patch-pixels model for part 0:

    splice_parts("runs/concat_w1", {0: "checkpoints/mini/wm_augmented"}, "runs/spliced")
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import torch

from wamplan.checkpoint import checkpoint_dir, read_config, read_meta, save_checkpoint
from wamplan.errors import UserError
from wamplan.worldmodel.splice import SPLICE_KIND, SplicedPredictor, spliced_record
from wamplan.worldmodel.load import KIND, load_world_model


def _concat_record(src: str | Path, what: str) -> tuple[Path, dict]:
    """(checkpoint dir, config) of ``src``, a world model on a ``concat`` encoder; one line for any other."""
    ckpt = checkpoint_dir(src)
    if read_meta(ckpt).get("kind") == SPLICE_KIND:
        base = read_config(ckpt, SPLICE_KIND).get("spliced", {}).get("base", "the concat model it was made from")
        raise UserError(f"{src} is a spliced model; only a concat model's own checkpoint can be {what}: use its base "
                        f"({base}), then splice the result")
    config = read_config(ckpt, KIND)
    name = (config.get("encoder") or {}).get("name")
    if name != "concat":
        raise UserError(f"{src} was trained on encoder {name!r}; only a concat model's parts can be {what} "
                        f"(wm train --encoder concat)")
    return ckpt, config


def reweigh_parts(src: str | Path, scales: Sequence[float], dst: str | Path) -> Path:
    """Write to ``dst`` the predictor of ``src`` (a run or checkpoint on a ``concat`` encoder) for the same encoder
    at ``scales`` (one positive number per part): its feature statistics scaled per part by new / old scale, its
    encoder record given the new scales. Returns the checkpoint directory. A model on another encoder, scales that
    are not one positive number per part, or a ``dst`` that exists, is refused in one line."""
    ckpt, config = _concat_record(src, "weighed anew")
    encoder = dict(config["encoder"])
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


def splice_parts(base: str | Path, parts: dict[int, str | Path], dst: str | Path) -> Path:
    """Write to ``dst`` the spliced model (kind ``wm-splice``) of ``base`` (a run or checkpoint on a ``concat``
    encoder) with part i predicted by ``parts[i]`` (a world model trained on exactly that part's encoder, of the
    same task). Returns the checkpoint directory. Any other base or part model, a part index the encoder lacks, or
    a ``dst`` that exists, is refused in one line."""
    if Path(dst).exists():
        raise UserError(f"{dst} exists; give a new directory for the spliced model (nothing is overwritten)")
    ckpt, config = _concat_record(base, "spliced")
    model, enc = load_world_model(ckpt)
    bad = [i for i in parts if isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < len(enc.parts)]
    if bad or not parts:
        raise UserError(f"parts {bad or '{}'} asked for; give {{part index: model}} for parts of the base's encoder, "
                        f"0-{len(enc.parts) - 1}")
    models, records = {}, {}
    for i, path in sorted(parts.items()):
        record = read_config(checkpoint_dir(path), KIND)
        theirs = {k: v for k, v in (record.get("encoder") or {}).items() if k != "path"}
        if theirs != config["encoder"]["parts"][i]:
            raise UserError(f"{path} was trained on encoder {theirs}, part {i} of {base} is "
                            f"{config['encoder']['parts'][i]}; give a model trained on that part's encoder")
        models[i], _ = load_world_model(path)
        if models[i].task.name != model.task.name:
            raise UserError(f"{path} predicts task '{models[i].task.name}', {base} '{model.task.name}'; splice "
                            f"models of one task")
        records[i] = record
    spliced = SplicedPredictor(model, models, [p.dim for p in enc.parts], enc.scales)
    made = {"base": str(ckpt), "parts": {str(i): str(checkpoint_dir(p)) for i, p in sorted(parts.items())}}
    return save_checkpoint(dst, spliced, {**spliced_record(spliced, config, records), "spliced": made},
                           kind=SPLICE_KIND)
