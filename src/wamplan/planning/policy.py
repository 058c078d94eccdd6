"""The planned policy: a WAM whose every chunk is refined by planning toward its own predicted images.

At a chunk boundary t the policy queries the *seed* WAM for its chunk and the *target* WAM for its
predicted t+H views (the same WAM unless an evaluation condition swaps in the expert oracle), encodes
the target views, and lets the planner search for the chunk whose predicted terminal embedding is
closest (paper §3.3). The planner only sees an objective; the dynamics backend decides what "predicted"
means (learned world model or simulator). The history frames the world model conditions on (H_ctx frames
at stride Δ, with the action blocks executed between them) are kept here.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from wamplan.config import field, require, to_dict
from wamplan.planning.base import Planner
from wamplan.planning.costs import CostFn
from wamplan.planning.dynamics import Dynamics, PlanningContext
from wamplan.policies.base import CAMERAS, Observation, Policy
from wamplan.wam.base import WAM, WAMOutput


@dataclass(frozen=True)
class PlannedPolicyConfig:
    first_chunk: str = field("open-loop", "open-loop (paper) or rest-history: plan chunk 1 from a synthesised history")
    plan_seed: int = field(0, "base seed of the planner's sampling (plus the chunk index)")

    def __post_init__(self):
        require(self.first_chunk in ("open-loop", "rest-history"),
                f"first_chunk must be open-loop or rest-history, got {self.first_chunk!r}")


class PlannedPolicy(Policy):
    name = "planned"

    def __init__(self, wam: WAM, planner: Planner, dynamics: Dynamics, encoder, cost: CostFn, *,
                 target_wam: WAM | None = None, config: PlannedPolicyConfig | None = None,
                 instruction: str | None = None):
        self.wam, self.target_wam = wam, target_wam or wam
        self.planner, self.dynamics, self.encoder, self.cost = planner, dynamics, encoder, cost
        self.config = config or PlannedPolicyConfig()
        self.instruction = instruction or getattr(wam, "default_instruction", "")
        self.chunk = wam.chunk_length
        self.frameskip = getattr(dynamics, "frameskip", self.chunk)
        self.context = getattr(dynamics, "context", 1)
        self.reset()

    # ------------------------------------------------------------------ Policy
    def reset(self, seed: int | None = None) -> None:
        self.wam.reset()
        if self.target_wam is not self.wam:
            self.target_wam.reset()
        self._queue: list[np.ndarray] = []
        self._hist: list[tuple[int, torch.Tensor, torch.Tensor]] = []  # (step, z (V, N, D), q (P,))
        self._executed: list[np.ndarray] = []
        self.chunks: list[dict[str, float]] = []
        self.last_plan = None
        self._episode_seed = seed or 0

    def wants_images(self, step: int) -> bool:
        return step % self.chunk == 0 or (self.dynamics.needs_history and step % self.frameskip == 0)

    def act(self, obs: Observation) -> np.ndarray:
        t = obs.step
        if self.dynamics.needs_history and t % self.frameskip == 0:
            self._hist.append((t, self._encode(obs.images), torch.as_tensor(obs.proprio)))
            self._hist = self._hist[-self.context:]
        if t % self.chunk == 0:
            self._queue = list(self._plan_chunk(obs))
        a = self._queue.pop(0)
        self._executed.append(np.clip(a, -1, 1))
        return a

    def info(self) -> dict[str, Any]:
        keys = ("wam_s", "target_encode_s", "search_s")
        planned = [c for c in self.chunks if c["planned"]]
        return dict(chunks=self.chunks, planned_chunks=len(planned),
                    mean_s={k: float(np.mean([c[k] for c in planned])) for k in keys} if planned else {})

    def config_dict(self) -> dict[str, Any]:
        return dict(name=self.name, wam=self.wam.config_dict(), target_wam=self.target_wam.config_dict(),
                    planner=type(self.planner).__name__, planner_config=to_dict(self.planner.config),
                    dynamics=type(self.dynamics).__name__, encoder=self.encoder.config_dict(), **to_dict(self.config))

    # ------------------------------------------------------------------ internals
    @torch.inference_mode()
    def _encode(self, images: dict[str, np.ndarray]) -> torch.Tensor:
        x = torch.from_numpy(np.stack([images[c] for c in CAMERAS])).to(self.encoder.device)  # (V, H, W, 3)
        return self.encoder.encode(x).float().cpu()  # (V, N, D)

    def _context(self, t: int) -> PlanningContext | None:
        """History frames at t-(Tc-1)Δ .. t and the action blocks between them; None if not available."""
        if not self.dynamics.needs_history:
            return None
        hist = self._hist
        if len(hist) == self.context and all(s == t - (self.context - 1 - i) * self.frameskip for i, (s, _, _) in enumerate(hist)):
            z = torch.stack([h[1] for h in hist])  # (Tc, V, N, D)
            q = torch.stack([h[2] for h in hist])  # (Tc, P)
            acts = np.stack(self._executed[hist[0][0]:t]) if t > hist[0][0] else np.zeros((0, 5), np.float32)
            a = torch.from_numpy(acts.reshape(self.context - 1, -1).astype(np.float32))  # (Tc-1, Δ·A)
            return PlanningContext(z, q, a)
        if self.config.first_chunk == "rest-history" and t == 0 and hist:
            _, z0, q0 = hist[-1]
            hold = np.zeros((self.frameskip, 5), np.float32)
            hold[:, 4] = 1.0  # arm still, gripper open
            a = torch.from_numpy(np.tile(hold.reshape(1, -1), (self.context - 1, 1)))  # (Tc-1, Δ·A)
            return PlanningContext(z0.expand(self.context, *z0.shape).clone(), q0.expand(self.context, -1).clone(), a)
        return None

    def _plan_chunk(self, obs: Observation) -> np.ndarray:
        t0 = time.perf_counter()
        seed_out: WAMOutput = self.wam.predict(obs, self.instruction)
        target_out = seed_out if self.target_wam is self.wam else self.target_wam.predict(obs, self.instruction)
        t1 = time.perf_counter()
        rec = dict(step=obs.step, planned=False, wam_s=t1 - t0, target_encode_s=0.0, search_s=0.0)
        self.chunks.append(rec)
        context = self._context(obs.step)
        if self.dynamics.needs_history and context is None:
            return seed_out.actions  # first chunk open loop (paper default): no history yet
        target = self._encode(target_out.images)  # (V, N, D)
        t2 = time.perf_counter()
        self.dynamics.prepare(context)
        covered = self.dynamics.covered(self.chunk)
        seed = torch.as_tensor(seed_out.actions)  # (H, A)
        result = self.planner.plan(seed[:covered], lambda cands: self.cost(self.dynamics.terminal(cands), target),
                                   seed=self.config.plan_seed + self._episode_seed * 1000 + obs.step)
        plan = np.concatenate([result.actions.cpu().numpy(), seed_out.actions[covered:]]).astype(np.float32)  # (H, A)
        rec.update(planned=True, target_encode_s=t2 - t1, search_s=time.perf_counter() - t2,
                   seed_cost=float(result.seed_cost) if result.seed_cost is not None else float("nan"),
                   best_cost=float(result.best_cost))
        self.last_plan = result
        return plan
