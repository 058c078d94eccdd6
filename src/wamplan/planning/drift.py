"""Drift search: a response-surface step on a smooth, low-dimensional correction of the WAM's chunk.

CEM executes the mean of its lowest-cost candidates, so with a ranker that orders candidates only roughly
the argmin and the elite mean follow its per-candidate errors (the winner's curse). This planner follows
the cost's large-scale slope instead. It searches only a *drift*: one constant per-step offset per searched
action dimension, added to every step of the WAM's chunk (for delta end-effector control, a path that bends
progressively toward a displaced end point; d = 4 numbers for x, y, z, yaw, the gripper frozen). Each
iteration scores the current chunk and ``num_candidates - 1`` drifts x ~ N(0, I) (in units of sigma), fits
a quadratic response surface

    c(x) ~ c0 + g.x + 1/2 x.Q.x          (1 + d + d(d+1)/2 coefficients, least squares over all candidates)

and moves to its minimiser x* = -Q^-1 g when Q is positive definite, else along -g, in both cases no farther
than ``step_radius`` (in sigma units) from the current centre. The regression uses every candidate's cost,
so errors of single candidates average out instead of picking the winner; the executed correction is a
smooth drift, never per-step jitter. sigma then shrinks by ``std_shrink`` and the next iteration refits
around the new centre. The final centre is returned. It suits a cost model whose argmin is unreliable but
whose slope is not.

Which dimensions are searched is the task's: ``search_dims`` left empty means the task's arm entries
(every action entry but the gripper), filled when the planned policy is built for a task
(:meth:`DriftConfig.for_task`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from wamplan.config import ConfigError
from wamplan.planning.base import SamplingPlanner, register_planner
from wamplan.planning.configs import DriftConfig


def quadratic_features(x: Tensor) -> Tensor:
    """x (B, d) -> (B, 1 + d + d(d+1)/2): 1, x_i, and x_i x_j for i <= j."""
    i, j = torch.triu_indices(x.shape[1], x.shape[1], device=x.device)  # (P,) each
    return torch.cat([torch.ones_like(x[:, :1]), x, x[:, i] * x[:, j]], dim=1)


def surface_step(x: Tensor, costs: Tensor, radius: float, ridge: float = 1e-4) -> tuple[Tensor, Tensor]:
    """Fit c(x) ~ c0 + g.x + 1/2 x.Q.x to costs (B,) at points x (B, d) and return (x* (d,), fitted c(x*)):
    the surface's minimiser when Q is positive definite, else the steepest-descent direction, cut to
    |x*| <= radius. NaN costs are left out of the fit."""
    ok = torch.isfinite(costs)
    x64, c = x[ok].double(), costs[ok].double()  # (B', d), (B',)
    d = x.shape[1]
    phi = quadratic_features(x64)  # (B', P)
    scale = c.abs().mean().clamp_min(1e-12)
    a = phi.T @ phi + ridge * len(c) * torch.eye(phi.shape[1], dtype=phi.dtype, device=phi.device)
    a[0, 0] -= ridge * len(c)  # the constant term is not shrunk
    beta = torch.linalg.solve(a, phi.T @ (c / scale))  # (P,)
    g = beta[1:1 + d]  # (d,)
    i, j = torch.triu_indices(d, d, device=x.device)
    q = torch.zeros(d, d, dtype=beta.dtype, device=beta.device)
    q[i, j] = beta[1 + d:]
    q = q + q.T  # x.Q.x / 2 = sum_{i<=j} b_ij x_i x_j: the diagonal is doubled, off-diagonals once each way
    evals = torch.linalg.eigvalsh(q)
    if bool(evals.min() > 1e-9):
        step = -torch.linalg.solve(q, g)  # (d,) the surface's minimiser
    else:
        step = -g / g.norm().clamp_min(1e-12) * radius  # (d,) downhill, as far as trusted
    norm = step.norm()
    if norm > radius:
        step = step * (radius / norm)
    fitted = (quadratic_features(step[None]) @ beta)[0] * scale
    return step.to(x.dtype), fitted.to(costs.dtype)


@register_planner("drift")
class DriftPlanner(SamplingPlanner):
    config_cls = DriftConfig
    config: DriftConfig

    def _begin(self, mu: Tensor, sigma: Tensor, frozen: Tensor) -> None:
        a = mu.shape[1]
        if not self.config.search_dims:
            raise ConfigError("drift needs search_dims: build the planned policy for a task (its arm entries fill "
                              "them), or pass --search-dims")
        if max(self.config.search_dims) >= a:
            raise ConfigError(f"search_dims {self.config.search_dims} name dimensions the {a}-D actions do not have; "
                              f"pass indices below {a}")
        keep = torch.ones(a, dtype=torch.bool, device=mu.device)  # (A,) True = stays the WAM's
        keep[list(self.config.search_dims)] = False
        sigma[:, keep] = 0.0
        frozen[:, keep] = True
        self._active = ~frozen[0]  # (A,) searched dimensions: one drift coefficient each
        d = int(self._active.sum())
        need = 1 + d + d * (d + 1) // 2
        if self.config.num_candidates <= need:
            raise ConfigError(f"drift fits {need} response-surface coefficients for {d} searched dimensions and needs "
                              f"more candidates than that; raise num_candidates above {need} or search fewer "
                              f"dimensions (search_dims)")

    def _noise(self, shape: tuple[int, int, int], gen: torch.Generator | None, device: torch.device) -> Tensor:
        b, h, a = shape
        return super()._noise((b, 1, a), gen, device).expand(b, h, a)  # (B', H_opt, A): one offset per chunk

    def _update(self, cand: Tensor, costs: Tensor, mu: Tensor, sigma: Tensor
                ) -> tuple[Tensor, Tensor, Tensor]:
        act = self._active  # (A,)
        x = ((cand - mu) / sigma.clamp_min(1e-12)).mean(dim=1)[:, act]  # (B, d) drift of each scored (clipped) candidate
        step, fitted = surface_step(x, costs, self.config.step_radius, self.config.ridge)  # (d,), ()
        drift = torch.zeros(mu.shape[1], dtype=mu.dtype, device=mu.device)  # (A,)
        drift[act] = step
        new_mu = mu + sigma * drift[None]  # (H_opt, A): the same offset at every step (sigma is per dim)
        return new_mu, sigma * self.config.std_shrink, fitted
