"""A small resumable training loop shared by the predictor and decoder trainers.

AdamW (weight decay on matrices only), linear warm-up then cosine decay (per step), gradient clipping,
a tqdm bar with loss and samples/s, validation at every epoch end (appended to ``metrics.jsonl``), and
a checkpoint directory ``out_dir/checkpoint`` (``wamplan.checkpoint``) written at every epoch end,
every ``save_every_steps``, on ``max_steps`` and on Ctrl-C.

Resuming is exact: the data order of epoch e is a permutation seeded by (seed, e) and the loop skips the
batches already done; weights, optimizer, scheduler, counters and the torch CPU RNG (dropout) are
restored. (A CUDA RNG is not saved: with dropout > 0 on a GPU, a resumed run differs from an
uninterrupted one only in its dropout masks.)
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Callable

import torch
from torch import nn
from torch.utils.data import DataLoader, Dataset
from tqdm.auto import tqdm

from wamplan.checkpoint import has_training_state, load_training_state, load_weights, read_config, save_checkpoint
from wamplan.errors import UserError
from wamplan.optim import make_adamw, optimizer_step, warmup_cosine
from wamplan.worldmodel.config import TrainConfig

CKPT_DIR = "checkpoint"
METRICS_FILE = "metrics.jsonl"
# TrainConfig fields that may change between a run and its resumption.
RUN_ONLY_FIELDS = ("num_workers", "save_every_steps")


def make_optimizer(model: nn.Module, cfg: TrainConfig) -> torch.optim.AdamW:
    return make_adamw(model, cfg.lr, cfg.weight_decay, cfg.betas)


def _to_device(batch: Any, device: torch.device) -> Any:
    if isinstance(batch, dict):
        return {k: _to_device(v, device) for k, v in batch.items()}
    return batch.to(device, non_blocking=True) if torch.is_tensor(batch) else batch


def _comparable(config: dict[str, Any]) -> str:
    """A config as canonical JSON with the run-only training fields left out."""
    c = json.loads(json.dumps(config))
    for f in RUN_ONLY_FIELDS:
        c.get("train", {}).pop(f, None)
    return json.dumps(c, sort_keys=True)


def checkpoint_path(path: str | Path) -> Path:
    """``path`` itself if it is a checkpoint directory, else ``path/checkpoint``."""
    p = Path(path)
    return p if (p / "config.json").is_file() else p / CKPT_DIR


def fit(model: nn.Module, train_set: Dataset, cfg: TrainConfig, *, kind: str, config: dict[str, Any],
        out_dir: str | Path, device: torch.device,
        loss_fn: Callable[[nn.Module, dict[str, torch.Tensor]], tuple[torch.Tensor, dict[str, float]]],
        evaluate: Callable[[nn.Module], dict[str, float]] | None = None,
        on_fresh_start: Callable[[], None] | None = None, resume: bool = False,
        max_steps: int | None = None, progress: bool = True, desc: str = "train") -> dict[str, Any]:
    """Train ``model`` (already on ``device``) with ``loss_fn(model, batch) -> (loss, logs)``.

    ``config`` is stored in the checkpoint (``kind`` names the model family); ``evaluate(model)`` runs
    under no_grad in eval mode after every epoch; ``on_fresh_start`` runs only when not resuming (e.g.
    to compute normalisation statistics). ``max_steps`` stops after that many optimisation steps in all
    (checkpointed, resumable). Returns the last metrics.
    """
    out = Path(out_dir)
    ckpt = out / CKPT_DIR
    bs = cfg.batch_size
    n = len(train_set)  # type: ignore[arg-type]
    steps_per_epoch = n // bs
    if steps_per_epoch < 1:
        raise UserError(f"training set has {n} items, fewer than batch_size {bs}; "
                        f"collect more data or lower --batch-size")
    total = steps_per_epoch * cfg.epochs
    opt = make_optimizer(model, cfg)
    sched = warmup_cosine(opt, round(cfg.warmup_epochs * steps_per_epoch), total, cfg.min_lr_ratio)
    state = {"epoch": 0, "step_in_epoch": 0, "global_step": 0}
    if has_training_state(ckpt) and not resume:
        raise UserError(f"{out} already holds a training checkpoint; pass --resume to continue it or a new --out")
    if resume and has_training_state(ckpt):
        if _comparable(read_config(ckpt, kind)) != _comparable(config):
            raise UserError(f"{ckpt} was trained with a different config; "
                            f"resume with the same config or use a new --out")
        load_weights(ckpt, model, device)
        saved = load_training_state(ckpt, opt, sched)
        if saved.get("steps_per_epoch") != steps_per_epoch:
            raise UserError(f"{ckpt} was trained with {saved.get('steps_per_epoch')} steps per epoch, this dataset "
                            f"gives {steps_per_epoch}; resume with the same dataset and batch size")
        state.update({k: saved[k] for k in state})
        torch.set_rng_state(torch.tensor(saved["rng_cpu"], dtype=torch.uint8))
    elif on_fresh_start is not None:
        on_fresh_start()
    out.mkdir(parents=True, exist_ok=True)

    def save() -> None:
        ts = dict(state, rng_cpu=torch.get_rng_state().tolist(), steps_per_epoch=steps_per_epoch)
        save_checkpoint(ckpt, model, config, kind=kind, optimizer=opt, scheduler=sched, train_state=ts)

    def log(record: dict[str, Any]) -> None:
        with open(out / METRICS_FILE, "a") as f:
            f.write(json.dumps(record) + "\n")

    metrics: dict[str, Any] = {"epoch": state["epoch"], "global_step": state["global_step"]}
    try:
        while state["epoch"] < cfg.epochs:
            epoch, start = state["epoch"], state["step_in_epoch"]
            g = torch.Generator().manual_seed(cfg.seed * 1_000_003 + epoch)
            order = torch.randperm(n, generator=g)[: steps_per_epoch * bs][start * bs:].tolist()
            loader = DataLoader(train_set, batch_size=bs, sampler=order, drop_last=True,
                                num_workers=cfg.num_workers, generator=g,
                                pin_memory=device.type != "cpu")
            bar = tqdm(total=steps_per_epoch, initial=start, desc=f"{desc} {epoch + 1}/{cfg.epochs}",
                       disable=not progress, dynamic_ncols=True)
            loss_sum, loss_n, t0, seen = 0.0, 0, time.perf_counter(), 0
            model.train()
            for batch in loader:
                batch = _to_device(batch, device)
                loss, logs = loss_fn(model, batch)
                optimizer_step(model, opt, sched, loss, cfg.grad_clip)
                state["global_step"] += 1
                state["step_in_epoch"] += 1
                loss_sum, loss_n, seen = loss_sum + float(loss.detach()), loss_n + 1, seen + bs
                bar.update(1)
                bar.set_postfix(loss=f"{loss_sum / loss_n:.4g}", sps=f"{seen / (time.perf_counter() - t0):.0f}",
                                lr=f"{sched.get_last_lr()[0]:.2e}")
                if cfg.save_every_steps and state["global_step"] % cfg.save_every_steps == 0:
                    save()
                if max_steps is not None and state["global_step"] >= max_steps:
                    break
            bar.close()
            if state["step_in_epoch"] < steps_per_epoch:  # stopped by max_steps inside the epoch
                save()
                return {"global_step": state["global_step"], "epoch": epoch, "stopped": "max_steps"}
            state["epoch"], state["step_in_epoch"] = epoch + 1, 0
            metrics = {"epoch": epoch + 1, "global_step": state["global_step"],
                       "train_loss": loss_sum / max(1, loss_n), "lr": sched.get_last_lr()[0],
                       "samples_per_s": seen / max(1e-9, time.perf_counter() - t0)}
            if evaluate is not None:
                model.eval()
                with torch.no_grad():
                    metrics.update({f"val/{k}": v for k, v in evaluate(model).items()})
                model.train()
            log(metrics)
            save()
            if progress:
                tqdm.write(f"{desc} epoch {epoch + 1}: " + " ".join(
                    f"{k}={v:.4g}" for k, v in metrics.items() if isinstance(v, float)))
            if max_steps is not None and state["global_step"] >= max_steps:
                return dict(metrics, stopped="max_steps")
    except KeyboardInterrupt:
        save()
        raise
    return metrics
