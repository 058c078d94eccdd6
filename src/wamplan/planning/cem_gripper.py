"""Gripper-aware CEM: the gripper is a discrete switch with its own categorical distribution.

Gaussian CEM never flips the WAM's gripper (``wamplan.planning.cem``). Here the continuous dimensions are
searched exactly as in CEM (Gaussian around the seed, refit to the elites), while the gripper dimension
of every candidate is one of a finite set of gripper sequences over the H_opt optimised steps:

* ``keep``: the WAM's own gripper values, verbatim (category 0);
* ``close@k``, k = 0..H_opt: open before step k, closed from step k on (``close@H_opt`` = open all chunk,
  ``close@0`` = closed all chunk);
* ``open@k``, k = 1..H_opt-1: closed before step k, open from step k on.

That is every gripper sequence with at most one switch (2·H_opt + 1 categories with ``keep``). Relative to
a WAM that closes at step s, ``close@k`` with k > s delays the grasp, k < s advances it, and ``close@H_opt``
cancels it (the same for releases with ``open@k``). This parameterisation needs no knowledge of the
gripper's current state (which a pure planner does not see): "hold closed" and "hold open" are both
categories, so keeping a grasp across the chunk boundary and dropping the cube are both candidates the
objective can tell apart. Two switches within one 16-step chunk (grasp and release) are not representable
except through ``keep``.

The categorical distribution starts as a prior centred on the WAM: a category's logit is minus its
Hamming distance (in steps) to the WAM's binarised gripper sequence divided by ``gripper_prior_steps``
(``keep`` has distance 0), so nearby switch times are likelier than far ones and none is excluded. Categories are
drawn by systematic resampling, so a near-uniform distribution over the 2·H_opt+1 categories visits nearly
every one of them in the first iteration (a random categorical sample can collapse onto the first few it
happens to draw). After each iteration the probabilities are refit to the elites' category frequencies,
mixed with the previous distribution by ``gripper_smoothing`` (0 = the plain CEM refit). Candidate 0 is
the current mean with the most probable category (ties: the lowest index, so ``keep`` first); the plan
returned is the final mean with the final most probable category.

The gripper's entry and its open and closed commands are the task's: left None in the config, they are filled
when the planned policy is built for a task (:meth:`CEMGripperConfig.for_task`). A task without a gripper has
nothing for this planner to switch: building it for one is a one-line error naming ``--planner cem`` (which
searches the same continuous dimensions), never a silent fall-back.
"""

from __future__ import annotations

import torch
from torch import Tensor

from wamplan.config import ConfigError
from wamplan.planning.base import register_planner
from wamplan.planning.cem import CEMPlanner
from wamplan.planning.configs import CEMGripperConfig


def gripper_categories(seed_gripper: Tensor, open_: float, closed: float) -> tuple[Tensor, list[str]]:
    """The candidate gripper sequences (C, H_opt) for the WAM's gripper values (H_opt,), and their names."""
    n = seed_gripper.shape[0]
    t = torch.arange(n, device=seed_gripper.device)  # (H_opt,)
    ks_close, ks_open = range(n + 1), range(1, n)
    close = torch.stack([torch.where(t < k, open_, closed) for k in ks_close])  # (H_opt+1, H_opt)
    rows = [seed_gripper.float()[None], close.float()]
    if n > 1:
        rows.append(torch.stack([torch.where(t < k, closed, open_) for k in ks_open]).float())  # (H_opt-1, H_opt)
    names = ["keep"] + [f"close@{k}" for k in ks_close] + [f"open@{k}" for k in ks_open]
    return torch.cat(rows), names  # (2·H_opt+1, H_opt)


def systematic_sample(probs: Tensor, n: int, gen: torch.Generator | None) -> Tensor:
    """n category indices (n,) drawn from probs (C,) by systematic resampling: one uniform offset u and the
    points (u + i) / n, so a category of mass p gets floor(n·p) or ceil(n·p) samples (low variance: a
    near-uniform distribution over C <= n categories covers every category)."""
    u = _rand1(gen, probs.device)  # (1,)
    points = (u + torch.arange(n, device=probs.device)) / n  # (n,) in [0, 1)
    cdf = torch.cumsum(probs, dim=0)  # (C,)
    return torch.searchsorted(cdf / cdf[-1], points).clamp_max(probs.numel() - 1)  # (n,)


def _rand1(gen: torch.Generator | None, device: torch.device) -> Tensor:
    if gen is None:
        return torch.rand(1, device=device)
    return torch.rand(1, generator=gen, device=gen.device).to(device)


@register_planner("cem-gripper")
class CEMGripperPlanner(CEMPlanner):
    config_cls = CEMGripperConfig
    config: CEMGripperConfig

    def prior(self, categories: Tensor) -> Tensor:
        """Initial probabilities (C,) of the categories (C, H_opt): softmax(-Hamming distance to keep / width)."""
        cfg = self.config
        mid = (cfg.gripper_open + cfg.gripper_closed) / 2
        is_open = (categories - mid) * (cfg.gripper_open - mid) > 0  # (C, H_opt) binarised
        dist = (is_open != is_open[0:1]).sum(dim=1).float()  # (C,), keep (row 0) at 0
        return torch.softmax(-dist / cfg.gripper_prior_steps, dim=0)  # (C,)

    # The shared sampling loop (SamplingPlanner.plan) with three hooks: the gripper column is taken out of the
    # Gaussian search (sigma 0) and filled per candidate with a sequence drawn from the categorical ``probs``,
    # which is refit to the elites; the mean's gripper is the most probable sequence.
    def _begin(self, mu: Tensor, sigma: Tensor, frozen: Tensor) -> None:
        cfg = self.config
        if None in (cfg.gripper_dim, cfg.gripper_open, cfg.gripper_closed):
            raise ConfigError("cem-gripper needs the gripper's entry and commands: build the planned policy for a "
                              "task (it fills them), or pass gripper_dim, gripper_open and gripper_closed")
        self._gd = gd = cfg.gripper_dim % mu.shape[1]
        frozen[:, gd] = True
        sigma[:, gd] = 0.0
        cats, self.category_names = gripper_categories(mu[:, gd], cfg.gripper_open, cfg.gripper_closed)
        self._cats = cats.clamp(cfg.action_low, cfg.action_high)  # (C, H_opt)
        self.last_probs = self.prior(self._cats)  # (C,) the categorical, final after plan (names in category_names)
        self._mode = torch.zeros((), dtype=torch.long, device=mu.device)  # keep

    def _shape_candidates(self, cand: Tensor, gen: torch.Generator | None) -> Tensor:
        cfg = self.config
        cat = systematic_sample(self.last_probs, cfg.num_candidates - int(cfg.include_mean), gen)  # (B',)
        if cfg.include_mean:
            cat = torch.cat([self._mode.view(1), cat])  # (B,), candidate 0 = the mode
        self._cat = cat
        cand[:, :, self._gd] = self._cats[cat]  # (B, H_opt) gripper sequences
        return cand

    def _refit(self, cand: Tensor, costs: Tensor, mu: Tensor, sigma: Tensor) -> tuple[Tensor, Tensor]:
        cfg, cat, probs = self.config, self._cat, self.last_probs
        sigma = sigma.clone()
        sigma[:, self._gd] = 0.0
        elite_idx = torch.argsort(torch.nan_to_num(costs, nan=float("inf")), stable=True)[: cfg.num_elites]
        freq = torch.bincount(cat[elite_idx], minlength=self._cats.shape[0]).float() / cfg.num_elites  # (C,)
        probs = (1 - cfg.gripper_smoothing) * freq + cfg.gripper_smoothing * probs  # (C,)
        first = torch.full_like(probs, float(len(elite_idx)))  # (C,) rank of each category's best elite
        first[cat[elite_idx].flip(0)] = torch.arange(len(elite_idx), device=probs.device).flip(0).float()
        self._mode = torch.argmax(probs - 1e-6 * first)  # most probable; ties: the one holding the better elite
        mu[:, self._gd] = self._cats[self._mode]  # the mean's gripper: the most probable sequence
        self.last_probs = probs
        return mu, sigma
