"""Checkpoints are directories: ``model.safetensors`` + ``config.json`` (+ ``training_state/`` to resume).

A training run keeps its checkpoint in ``RUN/checkpoint/`` (``wamplan.train_loop``); every loader takes
either the run directory or a checkpoint directory itself (:func:`checkpoint_dir`), so exported
checkpoints such as ``checkpoints/mini/tinywam`` load the same way.

Modules are never pickled; training state is saved as safetensors tensors plus a JSON of scalars, so
loading never needs ``torch.load(weights_only=False)``.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file

from wamplan.errors import UserError
from wamplan.provenance import provenance

MODEL_FILE = "model.safetensors"
CONFIG_FILE = "config.json"
STATE_DIR = "training_state"
CKPT_DIR = "checkpoint"  # a training run's checkpoint: RUN/checkpoint/


class CheckpointError(UserError):
    """A checkpoint directory is missing, incomplete or of another kind."""


def _atomic_dir(final: Path) -> Path:
    final.parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=f".{final.name}.tmp-", dir=final.parent))


def _swap_in(tmp: Path, final: Path) -> None:
    """Replace ``final`` by ``tmp`` so a crash leaves either the old or the new checkpoint, never half."""
    if final.exists():
        old = final.with_name(f".{final.name}.old-{os.getpid()}")
        os.replace(final, old)
        os.replace(tmp, final)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, final)


def _flat_optimizer_state(opt: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    sd = opt.state_dict()
    tensors, scalars = {}, {"param_groups": sd["param_groups"], "state": {}}
    for pid, st in sd["state"].items():
        scalars["state"][str(pid)] = {}
        for k, v in st.items():
            if torch.is_tensor(v):
                tensors[f"{pid}.{k}"] = v.detach().cpu().contiguous()
            else:
                scalars["state"][str(pid)][k] = v
    return tensors, scalars


def _restore_optimizer_state(opt: torch.optim.Optimizer, tensors: dict[str, torch.Tensor],
                             scalars: dict[str, Any]) -> None:
    state: dict[int, dict[str, Any]] = {int(pid): dict(st) for pid, st in scalars["state"].items()}
    for name, t in tensors.items():
        pid, k = name.split(".", 1)
        state.setdefault(int(pid), {})[k] = t
    opt.load_state_dict({"state": state, "param_groups": scalars["param_groups"]})


def save_checkpoint(path: str | Path, model: torch.nn.Module, config: dict[str, Any], *,
                    kind: str, optimizer: torch.optim.Optimizer | None = None,
                    scheduler: Any = None, train_state: dict[str, Any] | None = None) -> Path:
    """Write ``path/`` atomically. ``kind`` names the model class family (checked on load)."""
    final = Path(path)
    tmp = _atomic_dir(final)
    weights = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    save_file(weights, str(tmp / MODEL_FILE))
    meta = {"kind": kind, "config": config, "provenance": provenance()}
    (tmp / CONFIG_FILE).write_text(json.dumps(meta, indent=2) + "\n")
    if optimizer is not None:
        sdir = tmp / STATE_DIR
        sdir.mkdir()
        tensors, scalars = _flat_optimizer_state(optimizer)
        save_file(tensors, str(sdir / "optimizer.safetensors"))
        extra = {"optimizer": scalars, "train_state": train_state or {},
                 "scheduler": scheduler.state_dict() if scheduler is not None else None}
        (sdir / "state.json").write_text(json.dumps(extra) + "\n")
    _swap_in(tmp, final)
    return final


def checkpoint_dir(path: str | Path) -> Path:
    """``path`` itself if it is a checkpoint directory, else the checkpoint of the run ``path``."""
    p = Path(path)
    return p if (p / CONFIG_FILE).is_file() or not (p / CKPT_DIR / CONFIG_FILE).is_file() else p / CKPT_DIR


def read_config(path: str | Path, kind: str) -> dict[str, Any]:
    """The ``config`` section of a checkpoint of ``kind``; a clear error for anything else."""
    p = Path(path)
    cfg = p / CONFIG_FILE
    if not cfg.is_file() or not (p / MODEL_FILE).is_file():
        raise CheckpointError(f"{p} is not a wamplan checkpoint (needs {CONFIG_FILE} and {MODEL_FILE}); "
                              f"train one first or pass the right --ckpt")
    meta = json.loads(cfg.read_text())
    if meta.get("kind") != kind:
        raise CheckpointError(f"{p} holds a '{meta.get('kind')}' checkpoint, not '{kind}'; pass a {kind} checkpoint")
    return meta["config"]


def load_weights(path: str | Path, model: torch.nn.Module, device: str | torch.device = "cpu") -> None:
    model.load_state_dict(load_file(str(Path(path) / MODEL_FILE), device=str(device)))


def has_training_state(path: str | Path) -> bool:
    return (Path(path) / STATE_DIR / "state.json").is_file()


def load_training_state(path: str | Path, optimizer: torch.optim.Optimizer, scheduler: Any = None) -> dict[str, Any]:
    """Restore optimizer (and scheduler) state in place; return the saved ``train_state`` dict."""
    sdir = Path(path) / STATE_DIR
    extra = json.loads((sdir / "state.json").read_text())
    _restore_optimizer_state(optimizer, load_file(str(sdir / "optimizer.safetensors")), extra["optimizer"])
    if scheduler is not None and extra.get("scheduler") is not None:
        scheduler.load_state_dict(extra["scheduler"])
    return extra["train_state"]


def export_for_inference(src: str | Path, dst: str | Path, dtype: torch.dtype = torch.float16) -> Path:
    """Copy a checkpoint without its training state, floating-point weights cast to ``dtype`` (half the
    size for the demo checkpoints that ship in git; loading casts back to the model's dtype)."""
    src, final = Path(src), Path(dst)
    if not (src / MODEL_FILE).is_file():
        raise CheckpointError(f"{src} is not a checkpoint directory (no {MODEL_FILE})")
    tmp = _atomic_dir(final)
    weights = {k: (v.to(dtype) if v.is_floating_point() else v) for k, v in load_file(str(src / MODEL_FILE)).items()}
    save_file(weights, str(tmp / MODEL_FILE))
    meta = json.loads((src / CONFIG_FILE).read_text())
    meta["exported"] = {"from": str(src), "dtype": str(dtype).removeprefix("torch."), **provenance()}
    (tmp / CONFIG_FILE).write_text(json.dumps(meta, indent=2) + "\n")
    _swap_in(tmp, final)
    return final
