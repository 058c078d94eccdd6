"""Training the predictor (paper eq. 2, :mod:`wamplan.worldmodel.losses`) on windows of H_ctx + K frames, and
its held-out evaluation (:func:`evaluate_predictor`). A fine-tune starts from a checkpoint
(:mod:`wamplan.worldmodel.finetune`); a trained one loads with :mod:`wamplan.worldmodel.load`.

Normalisation: proprioception and actions are used as they are (roughly unit scale). Visual features
are normalised per dimension at the predictor's *input* with a mean/std (D,) computed from the training
set (``compute_feature_stats``) and kept as buffers in the checkpoint; outputs are scaled back, so the
loss (and the planner's cost, eq. 3) is in the raw feature space the encoder produces.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import torch
from torch.utils.data import DataLoader, Dataset

from wamplan.checkpoint import CKPT_DIR, checkpoint_dir, has_training_state, load_weights, read_config
from wamplan.config import to_dict
from wamplan.device import resolve_device
from wamplan.envs.spec import TaskSpec
from wamplan.errors import UserError
from wamplan.train_loop import DatasetBatches, evaluating, fit, saved_progress, shown
from wamplan.worldmodel.config import RETIRED_PREDICTOR_KEYS, RETIRED_TRAIN_KEYS, PredictorConfig, TrainConfig
from wamplan.worldmodel.finetune import check_init
from wamplan.worldmodel.load import KIND
from wamplan.worldmodel.losses import group_loss, per_horizon_mse, split_windows, window_loss
from wamplan.worldmodel.predictor import WorldModelPredictor, without_retired
from wamplan.worldmodel.siblings import evaluate_siblings


@torch.no_grad()
def evaluate_predictor(model: WorldModelPredictor, dataset: Dataset, horizon: int, gamma: float,
                       batch_size: int = 64, device: torch.device | None = None) -> dict[str, float]:
    """Per-horizon MSEs of the model and of the copy-the-last-context-frame baseline, and the loss."""
    device = device or next(model.parameters()).device
    sums: dict[str, torch.Tensor] = {}
    count = 0
    with evaluating(model):
        for batch in DataLoader(dataset, batch_size=batch_size, shuffle=False):
            batch = {k: v.to(device) for k, v in batch.items()}
            (zc, qc, ac), a_future, (zt, qt) = split_windows(model, batch, horizon)
            zp, qp = model.rollout(zc, qc, ac, a_future)  # (B, K, V, N, D), (B, K, P)
            parts = {"z_mse": per_horizon_mse(zp, zt), "q_mse": per_horizon_mse(qp, qt),
                     "copy_z_mse": per_horizon_mse(zc[:, -1:].expand_as(zt), zt),
                     "copy_q_mse": per_horizon_mse(qc[:, -1:].expand_as(qt), qt)}  # each (B, K)
            for k, v in parts.items():
                sums[k] = sums.get(k, 0) + v.sum(dim=0).double()  # (K,)
            count += zc.shape[0]
    w = gamma ** torch.arange(horizon, dtype=torch.float64)
    out: dict[str, float] = {}
    for k, v in sums.items():
        mean = (v / max(count, 1)).cpu()  # (K,)
        out.update({f"{k}_h{i + 1}": float(mean[i]) for i in range(horizon)})
    out["loss"] = float((w * (sums["z_mse"] + sums["q_mse"]).cpu() / max(count, 1)).sum())
    out["copy_loss"] = float((w * (sums["copy_z_mse"] + sums["copy_q_mse"]).cpu() / max(count, 1)).sum())
    return out


def compute_feature_stats(dataset: Dataset, max_items: int = 2000, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-dimension mean and std (D,) of the visual features over up to ``max_items`` random windows."""
    n = len(dataset)  # type: ignore[arg-type]
    idx = torch.randperm(n, generator=torch.Generator().manual_seed(seed))[:max_items].tolist()
    s = s2 = None
    count = 0
    for i in idx:
        z = dataset[i]["z"].double().flatten(0, -2)  # (T V N, D)
        s = z.sum(0) if s is None else s + z.sum(0)
        s2 = z.pow(2).sum(0) if s2 is None else s2 + z.pow(2).sum(0)
        count += z.shape[0]
    mean = s / count  # (D,)
    std = (s2 / count - mean.pow(2)).clamp_min(0).sqrt()  # (D,)
    return mean.float(), std.float()


def train_predictor(train_set: Dataset, cfg: PredictorConfig, train: TrainConfig, out_dir: str | Path, *,
                    val_set: Dataset | None = None, device: str | torch.device = "auto", resume: bool = False,
                    max_steps: int | None = None, progress: bool = True, encoder_info: dict[str, Any] | None = None,
                    data: dict[str, Any] | None = None, init: str | Path | None = None,
                    group_set: Dataset | None = None, val_groups: Dataset | None = None,
                    task: str | TaskSpec | None = None, cameras: Sequence[str] | None = None,
                    ) -> tuple[WorldModelPredictor, dict[str, Any]]:
    """Train (or resume) a predictor into the run directory ``out_dir`` (``wamplan.train_loop``:
    ``checkpoint/`` + ``metrics.jsonl``). ``encoder_info`` (e.g. ``encoder.config_dict()``) is stored as
    provenance; ``data`` identifies the training data (``data.store.describe_stores``), checked on resume.
    ``init`` (a predictor checkpoint with the same config and encoder) fine-tunes: a fresh run starts from its
    weights and feature statistics instead of a random initialisation and new statistics.
    ``group_set`` (``data.readers.BranchGroups``) adds :func:`group_loss` (the sibling and ranking losses, the
    latter on groups with targets) on ``train.sibling_groups`` groups to every step's loss; ``val_groups`` adds the
    held-out sibling error to the validation metrics (:func:`evaluate_siblings`), and with targets their ranking
    against them (:func:`sibling_ranking`). ``task`` and ``cameras`` (one per view) say what the windows
    show; the checkpoint records them, where given, in its ``data`` section (loading one that records no task
    means cube-insertion).
    Returns the trained model (eval mode) and the last metrics (with ``val/...`` entries if ``val_set``)."""
    dev = resolve_device(device) if isinstance(device, str) else device
    torch.manual_seed(train.seed)
    model = WorldModelPredictor(cfg, task, cameras).to(dev)
    trained_on = shown(model.task.name if model.task is not None else None, cameras)
    config = {"predictor": to_dict(cfg), "train": to_dict(train), "encoder": encoder_info,
              **({"data": trained_on} if trained_on else {})}
    if init is not None:
        config["init"] = str(Path(init).resolve())
        check_init(init, cfg, encoder_info)
    if resume:
        _refuse_retired_head(out_dir)

    def fresh_stats() -> None:
        if init is not None:
            load_weights(checkpoint_dir(init), model, dev, adapt=without_retired)  # an older start's heads dropped
            model.float()
        else:
            mean, std = compute_feature_stats(train_set, seed=train.seed)
            model.set_feature_stats(mean, std)

    def evaluate(m: torch.nn.Module) -> dict[str, float]:
        out = evaluate_predictor(m, val_set, train.horizon, train.gamma,  # type: ignore[arg-type]
                                 2 * train.batch_size, dev)
        if val_groups is not None and len(val_groups):  # type: ignore[arg-type]
            out.update(evaluate_siblings(m, val_groups, train.sibling_horizon, train.sibling_groups, dev))
        return out

    groups = None
    if group_set is not None and train.sibling_weight > 0:
        done = (saved_progress(out_dir) or {}).get("global_step", 0) if resume else 0
        groups = _group_batches(group_set, train, start=done)

    def step(m: WorldModelPredictor, b: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
        loss, logs = window_loss(m, b, train.horizon, train.gamma, train.loss_form, train.change_weight)
        if groups is not None:
            with torch.autocast(dev.type, enabled=False):  # --precision bfloat16: read and stack as stored
                g = {k: v.to(dev) for k, v in next(groups).items()}
            grp, grp_logs = group_loss(m, g, train)
            loss, logs = loss + grp, {**logs, **grp_logs}
        return loss, logs

    result = fit(model, DatasetBatches(train_set, train.num_workers, dev.type != "cpu"),
                 step, train, run_dir=out_dir, kind=KIND,
                 config=config, data=data, device=dev, evaluate=evaluate if val_set is not None else None,
                 on_fresh_start=fresh_stats, resume=resume, max_steps=max_steps,
                 progress=progress, desc="predictor", log=print if progress else None,
                 retired={"train": RETIRED_TRAIN_KEYS, "predictor": RETIRED_PREDICTOR_KEYS})
    return model.eval(), result.metrics


def _refuse_retired_head(out_dir: str | Path) -> None:
    """One line if the run in ``out_dir`` trained a spread head (``wm train --spread-weight``) or a state head
    (``--state-weight``), both removed: its weights and optimizer state hold the head, which this version no longer
    has, so it cannot resume. Its checkpoint still loads, without the head
    (:func:`~wamplan.worldmodel.predictor.without_retired`)."""
    ckpt = Path(out_dir) / CKPT_DIR
    if not has_training_state(ckpt):
        return
    saved = read_config(ckpt, KIND)
    predictor, train = saved.get("predictor", {}), saved.get("train", {})
    for head, built, weight in (("spread", "spread_head", "spread_weight"), ("state", "state_dim", "state_weight")):
        if predictor.get(built) or train.get(weight):
            raise UserError(f"{out_dir} was trained with a {head} head (wm train --{head}-weight), an option wamplan "
                            f"no longer has (it measured no gain): it cannot resume; use another --out, or fine-tune "
                            f"its checkpoint with --init (the head is dropped)")


def _group_batches(groups: Dataset, train: TrainConfig, start: int = 0):
    """Endless batches of ``train.sibling_groups`` branch groups, one per optimisation step from step ``start``:
    batch s is a function of (``train.seed``, s) alone, so a resumed run sees the batches it would have seen."""
    n, size = len(groups), train.sibling_groups  # type: ignore[arg-type]
    per_pass = n // size
    step = start
    while True:
        p, i = divmod(step, per_pass)
        order = torch.randperm(n, generator=torch.Generator().manual_seed(train.seed * 100_003 + p))
        items = [groups[j] for j in order[i * size:(i + 1) * size].tolist()]
        yield {k: torch.stack([it[k] for it in items]) for k in items[0]}  # each (B, G, T, ...)
        step += 1
