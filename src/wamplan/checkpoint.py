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
from typing import Any, Callable

import torch
from safetensors import SafetensorError
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


def read_json(path: str | Path, what: str = "checkpoint") -> Any:
    """A JSON file a checkpoint holds; a damaged one (not UTF-8, not JSON) is a one-line error naming it."""
    path = Path(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CheckpointError(f"{path} is damaged, not a JSON file ({type(e).__name__}: {e}); restore the {what} "
                              f"from a copy or train it again") from None


def read_meta(path: str | Path) -> dict[str, Any]:
    """The whole ``config.json`` of the checkpoint directory ``path`` (kind, config, provenance)."""
    p = Path(path)
    if not (p / CONFIG_FILE).is_file() or not (p / MODEL_FILE).is_file():
        raise CheckpointError(f"{p} is not a wamplan checkpoint (needs {CONFIG_FILE} and {MODEL_FILE}); "
                              f"train one first or fix the path")
    meta = read_json(p / CONFIG_FILE)
    if not isinstance(meta, dict) or not isinstance(meta.get("kind"), str) or \
            not isinstance(meta.get("config", {}), dict):
        raise CheckpointError(f"{p / CONFIG_FILE} is not a wamplan checkpoint config (a JSON object with 'kind' and "
                              f"'config'); restore the checkpoint from a copy or train it again")
    return meta


def read_config(path: str | Path, kind: str) -> dict[str, Any]:
    """The ``config`` section of a checkpoint of ``kind``; a clear error for anything else."""
    p = Path(path)
    meta = read_meta(p)
    if meta.get("kind") != kind or "config" not in meta:
        raise CheckpointError(f"{p} holds a '{meta.get('kind')}' checkpoint, not '{kind}'; pass a {kind} checkpoint")
    return meta["config"]


def load_tensors(path: str | Path, device: str | torch.device = "cpu") -> dict[str, torch.Tensor]:
    """The tensors of a safetensors file; a truncated or damaged one, or one whose tensors hold NaN (damage, or a
    run that diverged: no model computes with them), is a one-line error naming it, found here, on load."""
    try:
        tensors = load_file(str(path), device=str(device))
    except SafetensorError as e:
        raise CheckpointError(f"{path} is damaged or incomplete ({e}); restore it from a copy or train the "
                              f"checkpoint again") from None
    bad = [k for k, t in tensors.items() if t.is_floating_point() and bool(torch.isnan(t).any())]
    if bad:
        raise CheckpointError(f"{path} is damaged: tensor(s) {bad[:3]}{' ...' if len(bad) > 3 else ''} hold NaN "
                              f"(or its training diverged); restore it from a copy or train the checkpoint again")
    return tensors


def load_weights(path: str | Path, model: torch.nn.Module, device: str | torch.device = "cpu",
                 adapt: Callable[[dict[str, torch.Tensor]], dict[str, torch.Tensor]] | None = None) -> None:
    """Load ``path``'s weights into ``model`` (built from the same checkpoint's config.json); weights that do not
    fit the model are a one-line error naming the checkpoint. ``adapt`` maps the file's weights before they load
    (e.g. an older checkpoint's parts that this version no longer builds, dropped)."""
    weights = load_tensors(Path(path) / MODEL_FILE, device)
    if adapt is not None:
        weights = adapt(weights)
    try:
        model.load_state_dict(weights)
    except RuntimeError as e:  # size mismatch, missing or unexpected keys: the config no longer fits the weights
        details = [line.strip() for line in str(e).splitlines()[1:] if line.strip()]
        first = (details[0] if details else str(e).splitlines()[0]).rstrip(".")
        more = f" and {len(details) - 1} more" if len(details) > 1 else ""
        raise CheckpointError(f"{path}: this checkpoint's weights do not match its {CONFIG_FILE}: {first}{more}; "
                              f"restore the {CONFIG_FILE} it was saved with, or train it again") from None


def has_training_state(path: str | Path) -> bool:
    return (Path(path) / STATE_DIR / "state.json").is_file()


def load_training_state(path: str | Path, optimizer: torch.optim.Optimizer, scheduler: Any = None) -> dict[str, Any]:
    """Restore optimizer (and scheduler) state in place; return the saved ``train_state`` dict."""
    sdir = Path(path) / STATE_DIR
    extra = read_json(sdir / "state.json", "training run")
    _restore_optimizer_state(optimizer, load_tensors(sdir / "optimizer.safetensors"), extra["optimizer"])
    if scheduler is not None and extra.get("scheduler") is not None:
        scheduler.load_state_dict(extra["scheduler"])
    return extra["train_state"]


def export_for_inference(src: str | Path, dst: str | Path, dtype: torch.dtype = torch.float16) -> Path:
    """Copy a checkpoint without its training state, floating-point weights cast to ``dtype`` (half the
    size for the demo checkpoints that ship in git; loading casts back to the model's dtype). ``dst`` is new, or an
    exported checkpoint to replace; any other existing path (a run, a store, a folder of your files) is refused."""
    src, final = Path(src), Path(dst)
    if not (src / MODEL_FILE).is_file():
        raise CheckpointError(f"{src} is not a checkpoint directory (no {MODEL_FILE})")
    if final.exists() and (not final.is_dir() or {p.name for p in final.iterdir()} - {MODEL_FILE, CONFIG_FILE}):
        raise CheckpointError(f"{final} exists and is not an exported checkpoint (it holds other files); export "
                              f"into a new directory (nothing is overwritten)")
    weights = {k: (v.to(dtype) if v.is_floating_point() else v) for k, v in load_tensors(src / MODEL_FILE).items()}
    meta = read_meta(src)
    tmp = _atomic_dir(final)
    save_file(weights, str(tmp / MODEL_FILE))
    meta["exported"] = {"from": str(src), "dtype": str(dtype).removeprefix("torch."), **provenance()}
    (tmp / CONFIG_FILE).write_text(json.dumps(meta, indent=2) + "\n")
    _swap_in(tmp, final)
    return final
