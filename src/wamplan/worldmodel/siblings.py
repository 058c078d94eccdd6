"""Held-out metrics of a world model on branch groups (``data.readers.BranchGroups``: G windows that share their
context and differ in the chunk), what a planner needs of it: how its prediction moves with the chunk
(:func:`sibling_statistics`, pooled by :func:`pool_siblings`) and how it ranks the siblings against a target
(:func:`sibling_ranking`). Their training losses are in :mod:`wamplan.worldmodel.losses`.
"""

from __future__ import annotations

import torch
from torch.utils.data import DataLoader, Dataset

from wamplan.train_loop import evaluating
from wamplan.worldmodel.losses import SIBLING_SPLITS, sibling_errors, sibling_futures
from wamplan.worldmodel.predictor import WorldModelPredictor

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


@torch.no_grad()
def sibling_statistics(model: WorldModelPredictor, groups: Dataset, horizon: int, batch_size: int = 8,
                       device: torch.device | None = None, per: str = "group") -> dict[str, torch.Tensor]:
    """Each statistic of :func:`sibling_errors` for every group of ``groups``, (G_total, K) float64 on the CPU;
    ``per="view"``: (G_total, K, V), each view's own; ``per="token"``: (G_total, K, V, N), each token's;
    ``per="feature"``: (G_total, K, V, D), each feature dimension's within a view (:func:`pool_siblings` pools one
    view's ``[..., v]``, one token's ``[..., v, n]``; a sum over the last dim pools several)."""
    if per not in SIBLING_SPLITS:
        raise ValueError(f"per must be one of {', '.join(SIBLING_SPLITS)}, got {per!r}")
    device = device or next(model.parameters()).device
    parts: dict[str, list[torch.Tensor]] = {}
    with evaluating(model):
        for batch in DataLoader(groups, batch_size=batch_size, shuffle=False):
            for k, v in sibling_errors(model, {k: v.to(device) for k, v in batch.items()}, horizon, per).items():
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
