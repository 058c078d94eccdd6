"""The world model's losses (paper eq. 2) on windows of H_ctx + K frames, and the sibling and ranking losses on
branch groups.

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

A branch group (``data.readers.BranchGroups``) is G windows that share their context and differ in the chunk
executed from the current frame: z (B, G, T, V, N, D), ... :func:`sibling_loss` scores how the prediction moves
with the chunk; its held-out metrics are in :mod:`wamplan.worldmodel.siblings`.
"""

from __future__ import annotations

import torch

from wamplan.worldmodel.config import TrainConfig
from wamplan.worldmodel.predictor import WorldModelPredictor

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


def window_loss(model: WorldModelPredictor, batch: dict[str, torch.Tensor], horizon: int,
                gamma: float, loss_form: str = "mean", change_weight: float = 0.0
                ) -> tuple[torch.Tensor, dict[str, float]]:
    """Eq. 2: the discounted K-step autoregressive loss of a batch of windows. ``change_weight`` W > 0 weighs
    each token's squared error by :func:`change_weights` (the tokens that change count more); 0 is eq. 2."""
    (zc, qc, ac), a_future, (zt, qt) = split_windows(model, batch, horizon)
    zp, qp = model.rollout(zc, qc, ac, a_future)  # (B, K, V, N, D), (B, K, P)
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
    return loss, logs

SIBLING_SPLITS = ("group", "view", "token", "feature")  # how :func:`sibling_errors` splits a group's elements


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


def sibling_errors(model: WorldModelPredictor, batch: dict[str, torch.Tensor], horizon: int,
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
    s = sibling_errors(model, batch, horizon, futures=futures)
    err, spread = s["err"].mean(dim=0), s["spread"].mean(dim=0)  # (K,)
    w = gamma ** torch.arange(horizon, device=err.device, dtype=err.dtype)  # (K,)
    return (w * err).sum(), {f"sib_mse_h{horizon}": float(err[-1].detach()),
                             f"sib_rel_h{horizon}": float((err[-1] / spread[-1].clamp_min(1e-12)).detach())}


def group_loss(model: WorldModelPredictor, batch: dict[str, torch.Tensor], train: TrainConfig
               ) -> tuple[torch.Tensor, dict[str, float]]:
    """``train.sibling_weight`` times :func:`sibling_loss` of a batch of branch groups."""
    zp, zt, copy = sibling_futures(model, batch, train.sibling_horizon)
    loss, logs = zp.new_zeros(()), {}
    if train.sibling_weight > 0:
        sib, sib_logs = sibling_loss(model, batch, train.sibling_horizon, train.gamma, (zp, zt, copy))
        loss, logs = loss + train.sibling_weight * sib, {**logs, **sib_logs}
    return loss, logs
