"""Training TinyWAM on episode stores (``wamplan wam train``).

    loss = MSE(actions, expert chunk) + image_weight * {L1 | MSE}(predicted views at t+H, true views at t+H)

The stores are read once into memory at the model's ``image_size`` (frames shared between the items
that use them; ~37 kB a frame of three 64-px views), so an epoch costs only the network. Optional
augmentation shifts each view by a random whole number of pixels (border replicated), the same shift
for its current and its future picture, so the pair stays consistent.

Training runs in the shared loop (``wamplan.train_loop``): ``--out`` is a run directory
(``checkpoint/`` + ``metrics.jsonl``), re-running the same command resumes it exactly (the augmentation
of step s is seeded by (seed, s)), and a resumed run must use the same stores, sources and options.

The stores must hold one task; the model's unset action and proprio sizes and cameras are that task's
(:meth:`TinyWAMConfig.for_task`, the cameras the stores hold), and the checkpoint records the task's name
(``config["data"]["task"]``, what ``load_wam`` gives as ``wam.task``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Sequence

import torch
import torch.nn.functional as F
from torch.utils.data import DataLoader

from wamplan.checkpoint import CONFIG_FILE, CheckpointError, has_training_state, load_weights, read_config
from wamplan.config import from_dict, to_dict
from wamplan.device import resolve_device
from wamplan.errors import UserError
from wamplan.train_loop import (check_resume, check_run_dir, evaluating, fit, read_metrics, run_paths,
                                saved_progress)
from wamplan.wam.tinywam import KIND, TinyWAMConfig, TinyWAMNet, to_model_frames
from wamplan.wam.train_config import IMAGE_LOSSES, WAMTrainConfig  # noqa: F401  (its home)

# ----------------------------------------------------------------------------------------------- data
@dataclass
class WAMItems:
    """A split of WAM training items held in memory. Item i is the pair (frames[cur[i]], frames[fut[i]])."""

    frames: torch.Tensor  # (F, V, 3, S, S) uint8, each stored frame once
    cur: torch.Tensor  # (N,) int64, frame index at t
    fut: torch.Tensor  # (N,) int64, frame index at t + H
    proprio: torch.Tensor  # (N, P) float32 at t
    actions: torch.Tensor  # (N, H, A) float32, t .. t+H-1

    def __len__(self) -> int:
        return int(self.cur.shape[0])


def load_items(stores: Sequence[str | Path], cfg: TinyWAMConfig, split: str, val_fraction: float,
               sources: Sequence[str] | None = None, num_workers: int = 0) -> WAMItems:
    """Read the items of ``split`` from ``stores`` (of one task) into memory at ``cfg.image_size``; ``cfg``'s
    unset fields are the stores' task's."""
    from wamplan.data.readers import WAMSamples
    from wamplan.data.store import stores_task

    task, store_cameras = stores_task(stores)
    cfg = cfg.for_task(task, store_cameras)
    ds = WAMSamples(stores, chunk=cfg.chunk_length, split=split, val_fraction=val_fraction, sources=sources)
    views = [store_cameras.index(c) for c in cfg.cameras]  # the samples stack the stores' cameras in order
    keys: dict[tuple[int, int], int] = {}
    frames: list[torch.Tensor] = []
    cur, fut, proprio, actions = [], [], [], []

    def frame_index(key: tuple[int, int], img: torch.Tensor) -> int:
        if key not in keys:
            keys[key] = len(frames)
            frames.append(to_model_frames(img[views], cfg.image_size))  # (V, 3, S, S)
        return keys[key]

    loader = DataLoader(ds, batch_size=None, shuffle=False, num_workers=num_workers)
    for (i, k), item in zip(ds.items, loader):
        e = ds.episodes[i]
        t = e.image_steps[k]
        cur.append(frame_index((i, t), item["images"]))
        fut.append(frame_index((i, min(t + cfg.chunk_length, e.length)), item["future"]))
        proprio.append(item["proprio"].float())
        actions.append(item["actions"][:, :cfg.action_dim].float())
    S, V = cfg.image_size, len(views)
    return WAMItems(frames=torch.stack(frames) if frames else torch.zeros(0, V, 3, S, S, dtype=torch.uint8),
                    cur=torch.tensor(cur, dtype=torch.long), fut=torch.tensor(fut, dtype=torch.long),
                    proprio=torch.stack(proprio) if proprio else torch.zeros(0, cfg.proprio_dim),
                    actions=torch.stack(actions) if actions else torch.zeros(0, cfg.chunk_length, cfg.action_dim))


def compute_stats(items: WAMItems) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Image mean/std per channel (3,) in [0, 1] units over the frames; proprio mean/std (P,) over the items."""
    x = items.frames.double() / 255.0  # (F, V, 3, S, S)
    img_mean = x.mean(dim=(0, 1, 3, 4))  # (3,)
    img_std = x.std(dim=(0, 1, 3, 4))  # (3,)
    q = items.proprio.double()  # (N, P)
    return img_mean.float(), img_std.float(), q.mean(0).float(), (q.std(0) if len(q) > 1 else torch.ones_like(q[0])).float()


def random_shift(x: torch.Tensor, pad: int, generator: torch.Generator) -> torch.Tensor:
    """Shift each (B, V) slice of x (B, V, C, S, S) by whole pixels in [-pad, pad]^2, replicating the border."""
    B, V, C, S, _ = x.shape
    shifts = torch.randint(-pad, pad + 1, (B * V, 2), generator=generator)  # (BV, 2) pixels (dx, dy)
    base = torch.linspace(-1, 1, S, device=x.device)  # (S,) pixel centres (align_corners=True)
    gy, gx = torch.meshgrid(base, base, indexing="ij")  # (S, S) each
    step = 2.0 / (S - 1)
    off = shifts.to(x.device, x.dtype) * step  # (BV, 2)
    grid = torch.stack([gx[None] + off[:, 0, None, None], gy[None] + off[:, 1, None, None]], dim=-1)  # (BV, S, S, 2)
    y = F.grid_sample(x.reshape(B * V, C, S, S), grid, mode="nearest", padding_mode="border", align_corners=True)
    return y.view(B, V, C, S, S)


def make_batch(items: WAMItems, idx: torch.Tensor, device: torch.device, shift: int = 0,
               generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
    """A batch of items ``idx`` (B,): images/future (B, V, 3, S, S) float in [0, 1], proprio (B, P), actions (B, H, A)."""
    cur = items.frames[items.cur[idx]].to(device).float() / 255.0  # (B, V, 3, S, S)
    fut = items.frames[items.fut[idx]].to(device).float() / 255.0  # (B, V, 3, S, S)
    if shift > 0:
        assert generator is not None
        both = random_shift(torch.cat([cur, fut], dim=2), shift, generator)  # (B, V, 6, S, S): one shift per view
        cur, fut = both[:, :, :3], both[:, :, 3:]
    return {"images": cur, "future": fut, "proprio": items.proprio[idx].to(device),
            "actions": items.actions[idx].to(device)}


def wam_loss(net: TinyWAMNet, batch: dict[str, torch.Tensor], cfg: WAMTrainConfig) -> tuple[torch.Tensor, dict[str, float]]:
    actions, future = net(batch["images"], batch["proprio"])  # (B, H, A), (B, V, 3, S, S)
    act = F.mse_loss(actions, batch["actions"])
    img = (F.l1_loss if cfg.image_loss == "l1" else F.mse_loss)(future, batch["future"])
    return act + cfg.image_weight * img, {"act": act.item(), "img": img.item()}


@torch.no_grad()
def evaluate(net: TinyWAMNet, items: WAMItems, batch_size: int = 64, gripper: int | None = -1) -> dict[str, float]:
    """Validation metrics: action MSE (and that of the gripper entry ``gripper``, None: the task has none), image
    MSE of the clamped prediction, and the image MSE of the copy-the-current-view baseline (what a model that
    predicts no motion would get)."""
    device = next(net.parameters()).device
    sums = {"action_mse": 0.0, **({"gripper_mse": 0.0} if gripper is not None else {}), "image_mse": 0.0,
            "copy_image_mse": 0.0}
    with evaluating(net):
        for start in range(0, len(items), batch_size):
            idx = torch.arange(start, min(start + batch_size, len(items)))
            b = make_batch(items, idx, device)
            actions, future = net(b["images"], b["proprio"])  # (B, H, A), (B, V, 3, S, S)
            n = len(idx)
            sums["action_mse"] += float(F.mse_loss(actions, b["actions"])) * n
            if gripper is not None:
                sums["gripper_mse"] += float(F.mse_loss(actions[..., gripper], b["actions"][..., gripper])) * n
            sums["image_mse"] += float(F.mse_loss(future.clamp(0, 1), b["future"])) * n
            sums["copy_image_mse"] += float(F.mse_loss(b["images"], b["future"])) * n
    return {k: v / max(1, len(items)) for k, v in sums.items()}


@torch.no_grad()
def predicted_beside_future(net: TinyWAMNet, items: WAMItems, n: int = 4) -> Any:
    """The first view of ``n`` items spread over ``items``: TinyWAM's predicted view at the chunk's end beside the
    real one, (n * S, 2 * S, 3) uint8 (``train_log.beside_targets``)."""
    from wamplan.train_log import beside_targets

    idx = torch.linspace(0, len(items) - 1, min(n, len(items))).long()  # (n,)
    b = make_batch(items, idx, next(net.parameters()).device)
    _, future = net(b["images"], b["proprio"])  # (n, V, 3, S, S)
    return beside_targets(*(x[:, 0].permute(0, 2, 3, 1).float().cpu().numpy() for x in (future, b["future"])))


# ----------------------------------------------------------------------------------------------- training
class ItemBatches:
    """The :class:`~wamplan.train_loop.Batches` of in-memory items: the augmentation of global step s is
    seeded by (seed, s), so a resumed run draws the same shifts."""

    def __init__(self, items: WAMItems, device: torch.device, shift: int, seed: int) -> None:
        self.items, self.device, self.shift, self.seed = items, device, shift, seed

    def __len__(self) -> int:
        return len(self.items)

    def epoch(self, indices: list[int], batch_size: int, first_step: int) -> Iterator[dict[str, torch.Tensor]]:
        order = torch.tensor(indices, dtype=torch.long)  # (steps * B,)
        for j in range(len(indices) // batch_size):
            aug = torch.Generator().manual_seed(self.seed * 7_919 + first_step + j + 1)
            yield make_batch(self.items, order[j * batch_size:(j + 1) * batch_size], self.device, self.shift, aug)


@dataclass
class TrainResult:
    net: TinyWAMNet
    state: dict[str, Any]  # epoch, global_step, history (the epoch records of metrics.jsonl), ...
    finished_before: bool  # the run had already done all its epochs: nothing was trained


def train_tinywam(stores: Sequence[str | Path], out: str | Path, model_cfg: TinyWAMConfig | None = None,
                  train_cfg: WAMTrainConfig | None = None, *, sources: Sequence[str] | None = None,
                  max_steps: int | None = None, progress: bool = True, log=print) -> TrainResult:
    """Train TinyWAM on ``stores`` (of one task) into the run directory ``out``, or resume it if it holds a run.

    When resuming, the saved model config is used and the training config must match the saved one
    except for ``train_loop.RUN_ONLY_FIELDS``, and the data must be the same; ``model_cfg`` /
    ``train_cfg`` of None mean "as saved" (or the defaults for a new run). The model config's unset fields
    are the stores' task's. ``max_steps`` stops after that many optimisation steps in all (checkpointed; call
    again to continue)."""
    from wamplan.data.store import EpisodeStore, describe_stores
    from wamplan.data.store import stores_task

    out = Path(out)
    check_run_dir(out, "a TinyWAM checkpoint")
    ckpt, _ = run_paths(out)
    task, store_cameras = stores_task(stores)  # one line for stores of different tasks
    data = describe_stores(stores, sources)
    progress_saved = saved_progress(out)
    if (ckpt / CONFIG_FILE).is_file() and progress_saved is None:
        raise CheckpointError(f"{ckpt} holds a checkpoint without training state, so it cannot be resumed; pass a "
                              f"new --out")
    if progress_saved is not None:
        saved = read_config(ckpt, KIND)
        model_cfg = (model_cfg or from_dict(TinyWAMConfig, saved["model"])).for_task(task, store_cameras)
        train_cfg = train_cfg or from_dict(WAMTrainConfig, saved["train"])
        check_resume(out, KIND, {"model": to_dict(model_cfg), "train": to_dict(train_cfg)}, data)
    model_cfg = (model_cfg or TinyWAMConfig()).for_task(task, store_cameras)
    train_cfg = train_cfg or WAMTrainConfig()
    if progress_saved is not None and progress_saved["epoch"] >= train_cfg.epochs:  # say so before reading data
        net = TinyWAMNet(model_cfg)
        load_weights(ckpt, net)
        history = read_metrics(out, "epoch")
        last = history[-1] if history else {}
        log(f"{out} has already finished {progress_saved['epoch']} epochs ({progress_saved['global_step']} steps"
            + (f", val action_mse {last['val/action_mse']:.4g}" if "val/action_mse" in last else "")
            + f"); nothing to do. Pass --epochs > {progress_saved['epoch']} to train longer, or a new --out.")
        return TrainResult(net.eval(), dict(progress_saved, history=history), finished_before=True)
    device = resolve_device(train_cfg.device)

    t0 = time.perf_counter()
    train_items = load_items(stores, model_cfg, "train", train_cfg.val_fraction, sources, train_cfg.num_workers)
    val_items = load_items(stores, model_cfg, "val", train_cfg.val_fraction, sources, train_cfg.num_workers)
    n, bs = len(train_items), train_cfg.batch_size
    if n < bs:
        raise UserError(f"the training split has {n} items, fewer than batch_size {bs}; collect more episodes or "
                        f"lower --batch-size")
    log(f"data: {n} train items, {len(val_items)} val items, {len(train_items.frames) + len(val_items.frames)} "
        f"frames at {model_cfg.image_size} px in memory "
        f"({(train_items.frames.numel() + val_items.frames.numel()) / 2**20:.0f} MiB), read in "
        f"{time.perf_counter() - t0:.1f} s; device {device}")
    if len(val_items) == 0:
        log(f"note: no validation episodes at val_fraction {train_cfg.val_fraction}; collect more episodes or raise "
            f"--val-fraction to get validation losses")
    info = {"train_items": n, "val_items": len(val_items), "task": task.name,
            "camera_size": EpisodeStore(stores[0]).env.get("camera_size")}
    config = {"model": to_dict(model_cfg), "train": to_dict(train_cfg), "data": info}

    torch.manual_seed(train_cfg.seed)
    net = TinyWAMNet(model_cfg).to(device)

    def fresh_stats() -> None:
        net.set_stats(*[s.to(device) for s in compute_stats(train_items)])

    def validate(m: TinyWAMNet) -> dict[str, float]:
        return evaluate(m, val_items, 2 * bs, task.gripper_index)

    def pictures(m: TinyWAMNet) -> dict[str, Any]:
        return {"val/predicted_vs_future": predicted_beside_future(m, val_items)}

    result = fit(net, ItemBatches(train_items, device, train_cfg.shift_pixels, train_cfg.seed),
                 lambda m, b: wam_loss(m, b, train_cfg), train_cfg, run_dir=out, kind=KIND, config=config, data=data,
                 device=device, evaluate=validate if len(val_items) else None,
                 on_fresh_start=fresh_stats, resume=progress_saved is not None, max_steps=max_steps,
                 progress=progress, desc="tinywam", log=log, pictures=pictures if len(val_items) else None)
    return TrainResult(net.eval(), dict(result.state, history=result.history), finished_before=False)


def saved_configs(out: str | Path) -> tuple[TinyWAMConfig, WAMTrainConfig] | None:
    """The model and training configs of a resumable TinyWAM run at ``out``, else None."""
    ckpt, _ = run_paths(out)
    if not has_training_state(ckpt):
        return None
    saved = read_config(ckpt, KIND)
    return from_dict(TinyWAMConfig, saved["model"]), from_dict(WAMTrainConfig, saved["train"])
