"""Training the predictor (paper eq. 2) on windows of H_ctx + K frames.

A dataset item is a dict of one window of T >= H_ctx + K frames (frameskip Delta apart)::

    {"z": (T, V, N, D) float16/32 frozen features, "q": (T, P) float32, "a": (T, Delta*A) float32}

where ``a[t]`` is the block of Delta actions executed from frame t. From the H_ctx context frames the
predictor unrolls K steps autoregressively with the ground-truth actions (its predictions fed back), and

    loss = sum_{h=1..K} gamma**(h-1) * (MSE(z_pred_h, z_h) + MSE(q_pred_h, q_h))

with MSE the *mean* over elements (``loss_form="mean"``, our default). The paper writes squared norms,
||dz||^2 + ||dq||^2, which weight proprio by P / (V·N·D) against the features (10 / 6144 in the mini
preset, 10 / 602112 in the paper's), i.e. practically not at all; ``loss_form="sum"`` is that form divided
by V·N·D (the same optimum, a comparable scale).

``change_weight`` W > 0 (``TrainConfig``; 0 by default) weighs each visual token's squared error by how much
that token changes from the current frame (:func:`change_weights`: mean 1 over a window's tokens), so the few
tokens where the arm and the cube move are not drowned by the many static ones; logged as ``z_wmse_h1``.

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

from wamplan.checkpoint import checkpoint_dir, load_weights, read_config, read_meta
from wamplan.config import from_dict, to_dict
from wamplan.data.readers import STATE_UNIT_MM
from wamplan.device import resolve_device
from wamplan.envs.spec import TaskSpec
from wamplan.errors import UserError
from wamplan.train_loop import DatasetBatches, evaluating, fit, saved_progress, shown
from wamplan.worldmodel.config import PredictorConfig, TrainConfig
from wamplan.worldmodel.predictor import WorldModelPredictor
from wamplan.worldmodel.splice import SPLICE_KIND, load_spliced

KIND = "wm-predictor"
NEW_ON_INIT = ("state_head.", "spread_head.")  # weights a fine-tune may add to (or drop from) its --init checkpoint's


def split_windows(model: WorldModelPredictor, batch: dict[str, torch.Tensor], horizon: int):
    """Context, actions and targets of a batch of windows."""
    z, q, a = batch["z"].float(), batch["q"].float(), batch["a"].float()  # (B, T, V, N, D), (B, T, P), (B, T, DA)
    h = model.cfg.context
    if z.shape[1] < h + horizon:
        raise ValueError(f"windows hold {z.shape[1]} frames; need H_ctx + K = {h + horizon}")
    ctx = (z[:, :h], q[:, :h], a[:, :h - 1])  # (B, H, V, N, D), (B, H, P), (B, H-1, DA)
    a_future = a[:, h - 1:h - 1 + horizon]  # (B, K, DA), a_future[:, 0] executed from the current frame
    target = (z[:, h:h + horizon], q[:, h:h + horizon])  # (B, K, V, N, D), (B, K, P)
    return ctx, a_future, target


def per_horizon_mse(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """pred, target (B, K, ...) -> MSE per sample and step (B, K)."""
    return (pred - target).pow(2).flatten(2).mean(dim=-1)


def change_weights(z_cur: torch.Tensor, z_target: torch.Tensor, change_weight: float) -> torch.Tensor:
    """Per-token loss weights from how much each token changes: z_cur (B, V, N, D) the current frame, z_target
    (B, K, V, N, D) the K targets -> (B, K, V, N, 1) = (1 + W * c / mean_tokens(c)) / (1 + W), with c a token's
    mean squared change from the current frame; they average to 1 over the tokens of each window and step."""
    c = (z_target - z_cur[:, None]).pow(2).mean(dim=-1, keepdim=True)  # (B, K, V, N, 1)
    rel = c / c.mean(dim=(2, 3), keepdim=True).clamp_min(1e-12)  # (B, K, V, N, 1), mean 1 over (V, N)
    return (1 + change_weight * rel) / (1 + change_weight)


def state_loss(model: WorldModelPredictor, batch: dict[str, torch.Tensor], zp: torch.Tensor, zt: torch.Tensor,
               horizon: int) -> tuple[torch.Tensor, dict[str, float]]:
    """The state head's loss on a batch of windows, two terms that never mix:

    * the head learns to read the privileged targets ``batch["s"]`` (B, T, S) from every true frame's latent
      (the latents are frozen features, so this trains the head alone);
    * the predictor learns to make its predictions zp (B, K, V, N, D) read as the true frames zt (B, K, V, N, D)
      do, through the head with its weights held fixed: the squared difference of the two readings, whose
      gradient reaches the predictor only. The head is defined by the true latents, so the predictor cannot hide
      a private code of the state in its predictions; it can only get the directions of the latent that the head
      reads right.

    Logs the root-mean-square errors in mm of the head on true latents against the targets (``state_mm_true``) and
    of the predictions' reading against the true latents' at the first step (``state_mm_h1``)."""
    s = batch["s"].float()  # (B, T, S) cm
    e_true = (model.read_state(batch["z"].float()) - s).pow(2).mean()
    fixed = {k: v.detach() for k, v in model.state_head.named_parameters()}
    read = lambda z: torch.func.functional_call(model.state_head, fixed, (model.normalised(z),))  # noqa: E731
    e_pred = (read(zp) - read(zt).detach()).pow(2).mean(dim=(0, 2))  # (K,)
    mm = STATE_UNIT_MM
    return e_true + e_pred.mean(), {"state_mm_true": float(e_true.detach().sqrt()) * mm,
                                    "state_mm_h1": float(e_pred[0].detach().sqrt()) * mm}


def spread_terms(model: WorldModelPredictor, zp: torch.Tensor, zt: torch.Tensor, log_var: torch.Tensor
                 ) -> dict[str, torch.Tensor]:
    """Per sample and step (B, K): the spread head's Gaussian negative log-likelihood of the prediction's error
    (normalised units, constant dropped; each step's own mean zp is detached here, the predictions of earlier steps
    fed back into it are not), the variance
    ratio (squared error over predicted variance; 1 when calibrated), and, per token (mean over dims), the
    predicted variance and the squared error (B, K, V, N), for their correlation. zp, zt, log_var (B, K, V, N, D)."""
    r2 = ((zt.float() - zp.detach().float()) / model.z_std).pow(2)  # (B, K, V, N, D)
    lv = log_var.float()
    ratio = r2 * torch.exp(-lv)  # (B, K, V, N, D)
    return {"nll": 0.5 * (lv + ratio).flatten(2).mean(-1), "ratio": ratio.flatten(2).mean(-1),
            "tok_var": lv.exp().mean(-1), "tok_err": r2.mean(-1)}


def window_loss(model: WorldModelPredictor, batch: dict[str, torch.Tensor], horizon: int,
                gamma: float, loss_form: str = "mean", change_weight: float = 0.0, state_weight: float = 0.0,
                spread_weight: float = 0.0) -> tuple[torch.Tensor, dict[str, float]]:
    """Eq. 2: the discounted K-step autoregressive loss of a batch of windows. ``change_weight`` W > 0 weighs
    each token's squared error by :func:`change_weights` (the tokens that change count more); 0 is eq. 2.
    ``state_weight`` > 0 adds that times :func:`state_loss` (the batch must carry ``s``); ``spread_weight`` > 0
    that times the spread head's discounted negative log-likelihood (:func:`spread_terms`)."""
    (zc, qc, ac), a_future, (zt, qt) = split_windows(model, batch, horizon)
    zp, qp, *lv = model.rollout(zc, qc, ac, a_future, spread=spread_weight > 0)  # (B, K, V, N, D), (B, K, P)
    ez = per_horizon_mse(zp, zt).mean(dim=0)  # (K,)
    eq = per_horizon_mse(qp, qt).mean(dim=0)  # (K,)
    logs = {"z_mse_h1": float(ez[0].detach()), "q_mse_h1": float(eq[0].detach())}
    if change_weight > 0:
        w_tok = change_weights(zc[:, -1], zt, change_weight)  # (B, K, V, N, 1)
        ez = ((zp - zt).pow(2) * w_tok).flatten(2).mean(dim=-1).mean(dim=0)  # (K,) the weighted MSE
        logs["z_wmse_h1"] = float(ez[0].detach())
    q_weight = 1.0 if loss_form == "mean" else qt[0, 0].numel() / zt[0, 0].numel()  # sum form: P / (V·N·D)
    w = gamma ** torch.arange(horizon, device=ez.device, dtype=ez.dtype)  # (K,)
    loss = (w * (ez + q_weight * eq)).sum()
    if state_weight > 0:
        st, st_logs = state_loss(model, batch, zp, zt, horizon)
        loss, logs = loss + state_weight * st, {**logs, **st_logs}
    if spread_weight > 0:
        sp = spread_terms(model, zp, zt, lv[0])
        loss = loss + spread_weight * (w * sp["nll"].mean(dim=0)).sum()
        logs.update({f"spread_nll_h{horizon}": float(sp["nll"][:, -1].mean().detach()),
                     f"spread_ratio_h{horizon}": float(sp["ratio"][:, -1].mean().detach())})
    return loss, logs


SIBLING_SPLITS = ("group", "view", "token", "feature")  # how :func:`_sibling_errors` splits a group's elements


def _pool_elements(x: torch.Tensor, per: str) -> torch.Tensor:
    """(B, G, K, V, N, D) -> the mean over the siblings G and the elements of each part ``per`` splits into:
    (B, K) a group, (B, K, V) a view, (B, K, V, N) a token, (B, K, V, D) a feature of a view (over its tokens)."""
    if per == "feature":
        return x.mean(dim=4).mean(dim=1)
    return x.flatten({"group": 3, "view": 4, "token": 5}[per]).mean(dim=-1).mean(dim=1)


def sibling_futures(model: WorldModelPredictor, batch: dict[str, torch.Tensor], horizon: int
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A batch of branch groups (z (B, G, T, V, N, D), ...) -> the predicted, the true and the copied (current
    frame) futures, each (B, G, K, V, N, D)."""
    b, g = batch["z"].shape[:2]
    flat = {k: batch[k].flatten(0, 1) for k in ("z", "q", "a")}  # (B G, T, ...)
    (zc, qc, ac), a_future, (zt, _) = split_windows(model, flat, horizon)
    zp, _ = model.rollout(zc, qc, ac, a_future)  # (B G, K, V, N, D)
    copy = zc[:, -1:].expand_as(zt)  # (B G, K, V, N, D)
    return tuple(x.unflatten(0, (b, g)) for x in (zp, zt, copy))  # type: ignore[return-value]


def _ranks(x: torch.Tensor) -> torch.Tensor:
    """Ranks (0 = smallest) along the last dim."""
    return x.argsort(dim=-1).argsort(dim=-1).to(x.dtype)


def _rank_scores(p: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """Predicted and true costs (B, n) of n candidates -> (B, 3): Spearman's rho of the two orders, the regret (the
    true cost of the predicted best above the best one's, over an average pick's: 0 = the best, 1 = chance) and the
    top-1 hit."""
    n = p.shape[1]
    rho = 1 - 6 * (_ranks(p) - _ranks(r)).pow(2).sum(-1) / (n * (n * n - 1))  # (B,)
    best, pick = r.min(dim=1).values, r.gather(1, p.argmin(dim=1, keepdim=True))[:, 0]  # (B,)
    regret = (pick - best) / (r.mean(dim=1) - best).clamp_min(1e-12)
    return torch.stack([rho, regret, (p.argmin(dim=1) == r.argmin(dim=1)).to(p.dtype)], dim=-1)


def _rank_siblings(pred: torch.Tensor, true: torch.Tensor, target: torch.Tensor | None = None) -> torch.Tensor:
    """pred, true (B, G, F) outcomes of each group's G siblings -> (B, 3) :func:`_rank_scores` of ranking them by
    predicted cost (squared distance) to ``target`` (B, F); without one, of ranking the other siblings to each
    sibling's true outcome in turn, the mean over the G targets (see :func:`sibling_ranking`)."""
    pred, true = pred.double(), true.double()
    if target is not None:
        t = target.double()[:, None]  # (B, 1, F)
        return _rank_scores((pred - t).pow(2).sum(-1), (true - t).pow(2).sum(-1))
    g = pred.shape[1]
    p = torch.cdist(pred, true).pow(2)  # (B, i, j): predicted cost of sibling i to target j
    r = torch.cdist(true, true).pow(2)  # (B, i, j): its true cost
    out = []
    for j in range(g):
        others = [i for i in range(g) if i != j]
        out.append(_rank_scores(p[:, others, j], r[:, others, j]))
    return torch.stack(out, dim=1).mean(dim=1)  # (B, 3)


RANKING = ("rank_rho", "rank_regret", "rank_top1")


@torch.no_grad()
def sibling_ranking(model: WorldModelPredictor, groups: Dataset, horizon: int, batch_size: int = 8,
                    device: torch.device | None = None, targets: torch.Tensor | None = None
                    ) -> dict[str, torch.Tensor]:
    """How well the model ranks a group's siblings for a planner, per group (G_total,) float64 on the CPU.

    Each sibling's true outcome K frames on is, in turn, the target (or, with ``targets`` (G_total, V, N, D), each
    group's own target, e.g. the WAM's predicted views at the boundary, encoded); the other siblings (all of them
    with ``targets``) are ranked by the squared distance of their predicted outcome to it (the planner's cost) and
    compared with their true distance:
    ``rank_rho`` (Spearman's rho of the two orders; 1 = the same order), ``rank_regret`` (the true cost of the
    sibling the model picks above the best one's, over that of an average pick: 0 = it picks the best, 1 = no better
    than chance) and ``rank_top1`` (it picks the best), each a mean over the targets. The same three with the
    suffix ``_sib`` replace the predictions' group mean by the true one: the ranking if only how the prediction
    moves with the chunk (what ``sib_rel_hK`` scores) counted, without the error the siblings share."""
    device = device or next(model.parameters()).device
    if targets is not None and len(targets) != len(groups):  # type: ignore[arg-type]
        raise ValueError(f"{len(targets)} targets for {len(groups)} groups")  # type: ignore[arg-type]
    parts: list[torch.Tensor] = []
    done = 0
    with evaluating(model):
        for batch in DataLoader(groups, batch_size=batch_size, shuffle=False):
            g = batch["z"].shape[1]
            if g < (2 if targets is not None else 3):
                raise ValueError(f"groups of {g} siblings rank too few candidates; collect with --branches 3 or more")
            zp, zt, _ = sibling_futures(model, {k: v.to(device) for k, v in batch.items()}, horizon)
            zp, zt = zp[:, :, -1].flatten(2), zt[:, :, -1].flatten(2)  # (B, G, V N D) at step K
            t = None if targets is None else targets[done:done + len(zp)].flatten(1).to(zp.device)  # (B, V N D)
            done += len(zp)
            shared_removed = zp - zp.mean(dim=1, keepdim=True) + zt.mean(dim=1, keepdim=True)
            parts.append(torch.cat([_rank_siblings(zp, zt, t), _rank_siblings(shared_removed, zt, t)], dim=-1).cpu())
    x = torch.cat(parts)  # (G_total, 6)
    names = [*RANKING, *(f"{n}_sib" for n in RANKING)]
    return {n: x[:, i] for i, n in enumerate(names)}


def _sibling_errors(model: WorldModelPredictor, batch: dict[str, torch.Tensor], horizon: int,
                    per: str = "group", futures: tuple[torch.Tensor, ...] | None = None) -> dict[str, torch.Tensor]:
    """Per group of a batch of branch groups (z (B, G, T, V, N, D), ...), each (B, K), a mean over the siblings
    and elements (``per="view"``: each (B, K, V), a mean over the siblings and each view's elements;
    ``per="token"``: each (B, K, V, N), over the siblings and each token's features; ``per="feature"``: each
    (B, K, V, D), over the siblings and a view's tokens, feature by feature): ``err`` the squared error of
    the sibling-relative prediction, ``spread`` that of predicting no difference, ``cross`` the product of the
    predicted and true sibling differences (the gain: cross / spread), ``z_mse`` the siblings' plain latent error
    and ``copy_z_mse`` that of copying the current frame. ``futures`` (:func:`sibling_futures`'s three) reuses a
    rollout already made."""
    zp, zt, copy = futures if futures is not None else sibling_futures(model, batch, horizon)  # (B, G, K, V, N, D)
    dp, dt = zp - zp.mean(dim=1, keepdim=True), zt - zt.mean(dim=1, keepdim=True)  # relative to the group mean

    return {"err": _pool_elements((dp - dt).pow(2), per), "spread": _pool_elements(dt.pow(2), per),
            "cross": _pool_elements(dp * dt, per), "z_mse": _pool_elements((zp - zt).pow(2), per),
            "copy_z_mse": _pool_elements((copy - zt).pow(2), per)}


def sibling_loss(model: WorldModelPredictor, batch: dict[str, torch.Tensor], horizon: int,
                 gamma: float, futures: tuple[torch.Tensor, ...] | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """The sibling loss of a batch of branch groups (``data.readers.BranchGroups``): the G windows of a group share
    their context, so each one's predicted future minus the group's mean prediction must equal its true future
    minus the group's mean. The shared part of the error cancels: what is left is exactly how the prediction
    moves with the chunk, which is all that ranking CEM's candidates uses. Visual features only, like the
    planner's cost. Logs at step K: ``sib_mse`` and ``sib_rel`` (that error over the error of predicting no
    difference: 0 exact, 1 no better than predicting none; in training, a mean of per-step ratios). ``futures``
    (:func:`sibling_futures`'s three) reuses a rollout already made."""
    s = _sibling_errors(model, batch, horizon, futures=futures)
    err, spread = s["err"].mean(dim=0), s["spread"].mean(dim=0)  # (K,)
    w = gamma ** torch.arange(horizon, device=err.device, dtype=err.dtype)  # (K,)
    return (w * err).sum(), {f"sib_mse_h{horizon}": float(err[-1].detach()),
                             f"sib_rel_h{horizon}": float((err[-1] / spread[-1].clamp_min(1e-12)).detach())}


def cost_span(costs: torch.Tensor) -> torch.Tensor:
    """Costs (..., G) -> their range max - min (..., 1), floored at 1e-12."""
    return (costs.max(dim=-1, keepdim=True).values - costs.min(dim=-1, keepdim=True).values).clamp_min(1e-12)


def mppi_log_weights(costs: torch.Tensor, temperature: float, span: torch.Tensor | None = None) -> torch.Tensor:
    """Costs (..., G) of G candidates -> the log of MPPI's weights over them (..., G): softmax(-(c - min c) /
    (temperature * span)), with span (..., 1) the costs' own range by default: the planner's range-normalised
    weighting (``planning.mppi``)."""
    span = cost_span(costs) if span is None else span
    return torch.log_softmax(-costs / (temperature * span), dim=-1)  # the shift by min c cancels in the softmax


def rank_loss(model: WorldModelPredictor, batch: dict[str, torch.Tensor], horizon: int, temperature: float,
              futures: tuple[torch.Tensor, torch.Tensor] | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """The ranking loss of a batch of branch groups carrying their ``target`` (B, V, N, D)
    (``BranchGroups.with_targets``): each sibling's cost is the squared distance of its outcome ``horizon`` frames
    on to the target (the planner's patch cost, up to a constant); the loss is KL(true || predicted) between MPPI's
    weights of the siblings from their true and from their predicted costs (:func:`mppi_log_weights`), a mean over
    the groups: 0 when the model would weigh the siblings as the simulator does. Both are normalised by the TRUE
    costs' range (a predicted range near zero would scale the gradients without bound), so the predicted costs must
    also differ as much as the true ones do. ``futures`` (predicted, true
    outcomes, each (B, G, K, V, N, D)) reuses a rollout already made. Logs ``rank_kl`` and ``rank_top1`` (the model's
    lowest-cost sibling is the true one's)."""
    zp, zt = futures if futures is not None else sibling_futures(model, batch, horizon)[:2]
    t = batch["target"].to(zp.dtype)[:, None]  # (B, 1, V, N, D)
    pred = (zp[:, :, -1] - t).pow(2).flatten(2).mean(-1)  # (B, G)
    true = (zt[:, :, -1] - t).pow(2).flatten(2).mean(-1).detach()  # (B, G)
    span = cost_span(true)  # (B, 1)
    log_w, log_p = mppi_log_weights(true, temperature, span), mppi_log_weights(pred, temperature, span)  # (B, G)
    kl = (log_w.exp() * (log_w - log_p)).sum(-1).mean()
    top1 = (pred.argmin(-1) == true.argmin(-1)).float().mean()
    return kl, {"rank_kl": float(kl.detach()), "rank_top1": float(top1)}


def group_loss(model: WorldModelPredictor, batch: dict[str, torch.Tensor], train: TrainConfig
               ) -> tuple[torch.Tensor, dict[str, float]]:
    """``train.sibling_weight`` times :func:`sibling_loss` plus ``train.rank_weight`` times :func:`rank_loss` of a
    batch of branch groups, from one rollout of the siblings."""
    zp, zt, copy = sibling_futures(model, batch, train.sibling_horizon)
    loss, logs = zp.new_zeros(()), {}
    if train.sibling_weight > 0:
        sib, sib_logs = sibling_loss(model, batch, train.sibling_horizon, train.gamma, (zp, zt, copy))
        loss, logs = loss + train.sibling_weight * sib, {**logs, **sib_logs}
    if train.rank_weight > 0:
        rk, rk_logs = rank_loss(model, batch, train.sibling_horizon, train.rank_temperature, (zp, zt))
        loss, logs = loss + train.rank_weight * rk, {**logs, **rk_logs}
    return loss, logs


@torch.no_grad()
def sibling_statistics(model: WorldModelPredictor, groups: Dataset, horizon: int, batch_size: int = 8,
                       device: torch.device | None = None, per: str = "group") -> dict[str, torch.Tensor]:
    """Each statistic of :func:`_sibling_errors` for every group of ``groups``, (G_total, K) float64 on the CPU;
    ``per="view"``: (G_total, K, V), each view's own; ``per="token"``: (G_total, K, V, N), each token's;
    ``per="feature"``: (G_total, K, V, D), each feature dimension's within a view (:func:`pool_siblings` pools one
    view's ``[..., v]``, one token's ``[..., v, n]``; a sum over the last dim pools several)."""
    if per not in SIBLING_SPLITS:
        raise ValueError(f"per must be one of {', '.join(SIBLING_SPLITS)}, got {per!r}")
    device = device or next(model.parameters()).device
    parts: dict[str, list[torch.Tensor]] = {}
    with evaluating(model):
        for batch in DataLoader(groups, batch_size=batch_size, shuffle=False):
            for k, v in _sibling_errors(model, {k: v.to(device) for k, v in batch.items()}, horizon, per).items():
                parts.setdefault(k, []).append(v.double().cpu())  # (B, K) [, V [, N]]
    return {k: torch.cat(v) for k, v in parts.items()}


def pool_siblings(s: dict[str, torch.Tensor], horizon: int) -> dict[str, float]:
    """Pooled statistics of some groups from their :func:`sibling_statistics` ``s`` (each (n, K)): ``groups``;
    ``sib_mse_hK`` and ``sib_rel_hK``, the share of how sibling chunks' outcomes differ that the model misses
    (1 = no better than predicting no difference); ``sib_gain_hK``, the least-squares slope of the predicted
    sibling differences on the true ones (1 = the model moves its prediction with the chunk as much as the world
    does; below 1 it predicts only that share of a chunk's effect); the siblings' latent errors ``z_mse_h1``,
    ``z_mse_hK`` and, for scale, ``copy_z_mse_hK``."""
    k = horizon
    spread = max(float(s["spread"][:, -1].sum()), 1e-12)
    return {"groups": len(s["err"]), f"sib_mse_h{k}": float(s["err"][:, -1].mean()),
            f"sib_rel_h{k}": float(s["err"][:, -1].sum()) / spread,
            f"sib_gain_h{k}": float(s["cross"][:, -1].sum()) / spread,
            "z_mse_h1": float(s["z_mse"][:, 0].mean()), f"z_mse_h{k}": float(s["z_mse"][:, -1].mean()),
            f"copy_z_mse_h{k}": float(s["copy_z_mse"][:, -1].mean())}


def evaluate_siblings(model: WorldModelPredictor, groups: Dataset, horizon: int, batch_size: int = 8,
                      device: torch.device | None = None) -> dict[str, float]:
    """:func:`sibling_loss`'s error at step K on held-out branch groups, pooled over them (:func:`pool_siblings`):
    ``sib_mse_hK``, ``sib_rel_hK`` and ``sib_gain_hK``."""
    row = pool_siblings(sibling_statistics(model, groups, horizon, batch_size, device), horizon)
    return {k: row[k] for k in (f"sib_mse_h{horizon}", f"sib_rel_h{horizon}", f"sib_gain_h{horizon}")}


@torch.no_grad()
def evaluate_predictor(model: WorldModelPredictor, dataset: Dataset, horizon: int, gamma: float,
                       batch_size: int = 64, device: torch.device | None = None) -> dict[str, float]:
    """Per-horizon MSEs of the model and of the copy-the-last-context-frame baseline, and the loss."""
    device = device or next(model.parameters()).device
    sums: dict[str, torch.Tensor] = {}
    count = 0
    headed = model.spread_head is not None
    with evaluating(model):
        for batch in DataLoader(dataset, batch_size=batch_size, shuffle=False):
            batch = {k: v.to(device) for k, v in batch.items()}
            (zc, qc, ac), a_future, (zt, qt) = split_windows(model, batch, horizon)
            zp, qp, *lv = model.rollout(zc, qc, ac, a_future, spread=headed)  # (B, K, V, N, D), (B, K, P)
            parts = {"z_mse": per_horizon_mse(zp, zt), "q_mse": per_horizon_mse(qp, qt),
                     "copy_z_mse": per_horizon_mse(zc[:, -1:].expand_as(zt), zt),
                     "copy_q_mse": per_horizon_mse(qc[:, -1:].expand_as(qt), qt)}  # each (B, K)
            if model.state_head is not None and "s" in batch:  # squared state errors (cm^2), mean over S
                st = batch["s"][:, model.cfg.context:model.cfg.context + horizon].float()  # (B, K, S)
                parts["state_pred_se"] = (model.read_state(zp) - st).pow(2).mean(dim=-1)  # (B, K)
                parts["state_true_se"] = (model.read_state(zt) - st).pow(2).mean(dim=-1)  # (B, K)
                parts["state_gap_se"] = (model.read_state(zp) - model.read_state(zt)).pow(2).mean(dim=-1)  # (B, K)
            if headed:  # the spread head's fit, and the sums of the per-token log-log correlation
                sp = spread_terms(model, zp, zt, lv[0])
                x, y = sp["tok_var"].log().flatten(2).double(), sp["tok_err"].clamp_min(1e-12).log().flatten(2).double()
                parts.update({"spread_nll": sp["nll"], "spread_ratio": sp["ratio"], "tok_x": x.mean(-1),
                              "tok_y": y.mean(-1), "tok_xy": (x * y).mean(-1), "tok_xx": (x * x).mean(-1),
                              "tok_yy": (y * y).mean(-1)})  # each (B, K)
            for k, v in parts.items():
                sums[k] = sums.get(k, 0) + v.sum(dim=0).double()  # (K,)
            count += zc.shape[0]
    w = gamma ** torch.arange(horizon, dtype=torch.float64)
    out: dict[str, float] = {}
    for k, v in sums.items():
        mean = (v / max(count, 1)).cpu()  # (K,)
        out.update({f"{k}_h{i + 1}": float(mean[i]) for i in range(horizon)})
    if headed:  # Pearson correlation, over held-out tokens, of log predicted variance with log squared error
        m = {k: v.cpu() / max(count, 1) for k, v in sums.items() if k.startswith("tok_")}  # (K,) each
        cov = m["tok_xy"] - m["tok_x"] * m["tok_y"]
        corr = cov / ((m["tok_xx"] - m["tok_x"] ** 2) * (m["tok_yy"] - m["tok_y"] ** 2)).clamp_min(1e-24).sqrt()
        out.update({f"spread_corr_h{i + 1}": float(corr[i]) for i in range(horizon)})
        out = {k: v for k, v in out.items() if not k.startswith("tok_")}
    for k in ("state_pred", "state_true", "state_gap"):  # root-mean-square state errors in mm
        for i in range(horizon):
            if f"{k}_se_h{i + 1}" in out:
                out[f"{k}_mm_h{i + 1}"] = out.pop(f"{k}_se_h{i + 1}") ** 0.5 * STATE_UNIT_MM
    out["loss"] = float((w * (sums["z_mse"] + sums["q_mse"]).cpu() / max(count, 1)).sum())
    out["copy_loss"] = float((w * (sums["copy_z_mse"] + sums["copy_q_mse"]).cpu() / max(count, 1)).sum())
    return out


def fit_state_head(model: WorldModelPredictor, dataset: Dataset, max_items: int = 1500, seed: int = 0) -> None:
    """Start a 'ridge' state head from the ridge fit of the privileged targets on the true latents of up to
    ``max_items`` random windows of ``dataset`` (every frame of each)."""
    n = len(dataset)  # type: ignore[arg-type]
    idx = torch.randperm(n, generator=torch.Generator().manual_seed(seed))[:max_items].tolist()
    items = [dataset[i] for i in idx]
    z = torch.cat([it["z"].float() for it in items])  # (n T, V, N, D)
    s = torch.cat([it["s"].float() for it in items])  # (n T, S)
    dev = model.z_mean.device
    model.state_head.fit_ridge(model.normalised(z.to(dev)), s.to(dev))


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
    weights and feature statistics instead of a random initialisation and new statistics; with a ``concat``
    encoder whose first part is the checkpoint's encoder it starts grown (:func:`grow_weights`).
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
    old_dim = None
    if init is not None:
        config["init"] = str(Path(init).resolve())
        old_dim = _check_init(init, cfg, encoder_info)
    if train.spread_only:
        if init is None or old_dim is not None or model.spread_head is None:
            raise UserError("--spread-only fits a spread head onto a trained model: pass its checkpoint as --init "
                            "(with the same encoder) and --spread-weight W > 0")
        for name, p in model.named_parameters():  # the mean predictions stay the --init checkpoint's
            p.requires_grad_(name.startswith("spread_head."))

    def fresh_stats() -> None:
        if init is not None:
            load_weights(checkpoint_dir(init), model, dev, new=NEW_ON_INIT,
                         adapt=None if old_dim is None else lambda w: grow_weights(w, model, old_dim))
            model.float()
            if old_dim is not None:  # the grown dims' statistics from the data, the start's kept for its own
                mean, std = compute_feature_stats(train_set, seed=train.seed)
                model.set_feature_stats(torch.cat([model.z_mean[:old_dim].cpu(), mean[old_dim:]]),
                                        torch.cat([model.z_std[:old_dim].cpu(), std[old_dim:]]))
        else:
            mean, std = compute_feature_stats(train_set, seed=train.seed)
            model.set_feature_stats(mean, std)
        if model.state_head is not None and cfg.state_head == "ridge" and not train.spread_only:
            fit_state_head(model, train_set, seed=train.seed)  # with --spread-only the --init's head is kept

    def evaluate(m: torch.nn.Module) -> dict[str, float]:
        out = evaluate_predictor(m, val_set, train.horizon, train.gamma,  # type: ignore[arg-type]
                                 2 * train.batch_size, dev)
        if val_groups is not None and len(val_groups):  # type: ignore[arg-type]
            out.update(evaluate_siblings(m, val_groups, train.sibling_horizon, train.sibling_groups, dev))
            targets = getattr(val_groups, "targets", None)
            if targets is not None:  # how the held-out siblings rank against their targets (the ranking loss's aim)
                r = sibling_ranking(m, val_groups, train.sibling_horizon, train.sibling_groups, dev, targets)
                out.update({k: float(r[k].mean()) for k in RANKING})
        return out

    groups = None
    if group_set is not None and (train.sibling_weight > 0 or train.rank_weight > 0):
        if train.rank_weight > 0 and getattr(group_set, "targets", None) is None:
            raise ValueError("rank_weight > 0 needs branch groups with targets (BranchGroups.with_targets)")
        done = (saved_progress(out_dir) or {}).get("global_step", 0) if resume else 0
        groups = _group_batches(group_set, train, start=done)

    def step(m: WorldModelPredictor, b: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
        loss, logs = window_loss(m, b, train.horizon, train.gamma, train.loss_form, train.change_weight,
                                 train.state_weight, train.spread_weight)
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
                 progress=progress, desc="predictor", log=print if progress else None)
    return model.eval(), result.metrics


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


def _check_init(init: str | Path, cfg: PredictorConfig, encoder_info: dict[str, Any] | None) -> int | None:
    """A fine-tuning start must be a predictor of the same architecture over the same encoder's tokens, or one this
    run grows (:func:`grown_dims`). Returns the start's token size D when it is grown, else None."""
    saved = read_config(checkpoint_dir(init), KIND)
    theirs = to_dict(from_dict(PredictorConfig, saved["predictor"]))  # fields added since it was saved: their defaults
    theirs.update(state_dim=cfg.state_dim, state_head=cfg.state_head,  # a fine-tune may add (or drop) a state head
                  spread_head=cfg.spread_head)  # or a spread head
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
    load_weights(ckpt, model)
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
