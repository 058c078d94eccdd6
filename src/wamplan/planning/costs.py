"""Planning costs: distance between predicted terminal embeddings and the WAM's target embedding.

A cost maps predictions for B candidates and ONE target to B costs, lower is better:

    patch: pred (B, V, N, D), target (V, N, D) -> (B,)   the paper's eq. 3
    cls:   pred (B, V, D),    target (V, D)    -> (B,)   one vector per view: a class token, or, given
                                                         patch tokens (B, V, N, D) and (V, N, D), their mean

Eq. 3 is the mean squared distance pooled over views, patches and dims, C = ||z_WM - z_WAM||^2 / |z|.
Optional ``view_weights`` (V,) pool the per-view MSEs by a weighted average instead (normalised to
sum 1; uniform weights give eq. 3 exactly); a zero weight drops a camera, e.g. (0, 0, 1) = wrist only.
Costs are computed in float32 whatever the prediction dtype (bf16 squared distances are too coarse
to rank candidates).
"""

from __future__ import annotations

import functools
import math
from typing import Callable, Sequence

import torch
from torch import Tensor

from wamplan.config import require
from wamplan.planning.cost_config import COST_NAMES, CostConfig
from wamplan.registry import Registry

CostFn = Callable[[Tensor, Tensor], Tensor]  # (pred (B, V, ...), target (V, ...)) -> (B,)
COSTS = Registry("cost")


def register_cost(name: str) -> Callable[[CostFn], CostFn]:
    """Decorator: make ``fn(pred, target, view_weights=None) -> (B,)`` a cost by name (``CostConfig(name=...)``,
    ``--cost-name``)."""
    def deco(fn: CostFn) -> CostFn:
        COSTS.register(name)(fn)
        COST_NAMES.add(name)
        return fn

    return deco


def _check(pred: Tensor, target: Tensor, layout: str) -> None:
    dims = len(layout.split(","))  # e.g. "V, N, D" -> 3
    if pred.dim() != dims + 1 or target.shape != pred.shape[1:]:
        hint = "drop the target's batch dimension" if target.dim() == pred.dim() else \
            "give the target the predictions' shape without their batch dimension"
        raise ValueError(f"expected predictions (B, {layout}) and a target ({layout}), got "
                         f"{tuple(pred.shape)} and {tuple(target.shape)}; {hint}")


def _pool_views(per_view: Tensor, view_weights: Tensor | None) -> Tensor:
    """(B, V) per-view MSE -> (B,): plain mean, or the weighted average with weights (V,)."""
    if view_weights is None:
        return per_view.mean(dim=1)  # (B,)
    if view_weights.shape != per_view.shape[1:]:
        raise ValueError(f"view_weights has {view_weights.numel()} entries for {per_view.shape[1]} "
                         f"views; give one weight per camera view")
    w = view_weights.to(per_view)  # (V,) on the predictions' device
    w = w / w.sum()  # (V,) sums to 1
    return per_view @ w  # (B,)


@register_cost("patch")
def patch_cost(pred: Tensor, target: Tensor, view_weights: Tensor | None = None) -> Tensor:
    """Eq. 3: MSE over views, patches and dims. pred (B, V, N, D), target (V, N, D) -> (B,)."""
    _check(pred, target, "V, N, D")
    sq = (pred.float() - target.float().unsqueeze(0)).square()  # (B, V, N, D)
    return _pool_views(sq.mean(dim=(2, 3)), view_weights)  # (B, V) -> (B,)


@register_cost("cls")
def cls_cost(pred: Tensor, target: Tensor, view_weights: Tensor | None = None) -> Tensor:
    """MSE of one vector per view, over views and dims. pred (B, V, D), target (V, D) -> (B,); patch tokens
    (B, V, N, D) and (V, N, D) are pooled to their mean over the N tokens first (a global, not a spatial, match)."""
    if pred.dim() == 4 and target.dim() == 3:
        pred, target = pred.float().mean(dim=2), target.float().mean(dim=1)  # (B, V, D), (V, D)
    _check(pred, target, "V, D")
    diff = pred.float() - target.float().unsqueeze(0)  # (B, V, D)
    return _pool_views(diff.square().mean(dim=2), view_weights)  # (B, V) -> (B,)


def make_cost(name: str = "patch", view_weights: Sequence[float] | None = None) -> CostFn:
    """The cost ``name`` as ``fn(pred, target) -> (B,)``, with optional per-view weights (V,)."""
    fn = COSTS.lookup(name)
    if not view_weights:
        return fn
    require(all(w >= 0 for w in view_weights) and sum(view_weights) > 0,
            f"view_weights must be >= 0 with a positive sum, got {tuple(view_weights)}")
    weights = torch.tensor(tuple(view_weights), dtype=torch.float32)  # (V,), moved per call
    return functools.partial(fn, view_weights=weights)


def pool_fits(num_tokens: int, k: int) -> bool:
    """Whether ``num_tokens`` form a square grid whose side ``k`` divides (what :func:`pool_tokens` needs)."""
    side = math.isqrt(num_tokens)
    return side * side == num_tokens and side % k == 0


def pool_tokens(z: Tensor, k: int) -> Tensor:
    """(..., N, D) tokens of a square g x g grid (row-major) -> (..., (g/k)^2, D): the mean of each k x k block;
    a ValueError when N is not a square whose side k divides."""
    *lead, n, d = z.shape
    g = math.isqrt(n)
    if not pool_fits(n, k):
        raise ValueError(f"pooling {k} x {k} needs a square token grid whose side {k} divides; got {n} tokens "
                         f"per view: lower --cost-pool")
    blocks = z.float().reshape(*lead, g // k, k, g // k, k, d)  # (..., g/k, k, g/k, k, D)
    return blocks.mean(dim=(-4, -2)).reshape(*lead, (g // k) ** 2, d)  # (..., (g/k)^2, D)


def with_pooling(cost: CostFn, k: int) -> CostFn:
    """``cost`` on tokens pooled k x k per view (:func:`pool_tokens`). pred (B, V, N, D), target (V, N, D) -> (B,)."""
    def fn(pred: Tensor, target: Tensor) -> Tensor:
        return cost(pool_tokens(pred, k), pool_tokens(target, k))

    return fn


def build_cost(cfg: CostConfig) -> CostFn:
    """The cost ``cfg`` names, with its view weights and token pooling."""
    cost = make_cost(cfg.name, cfg.view_weights or None)
    if cfg.pool > 1:
        cost = with_pooling(cost, cfg.pool)
    return cost
