"""The planned policy: a WAM whose every chunk is refined by planning toward its own predicted images.

At a chunk boundary t the policy queries the *seed* WAM for its chunk and the *target* WAM for its
predicted t+H views (the same WAM unless an evaluation condition swaps in the expert oracle), encodes
the target views, and lets the planner search for the chunk whose predicted terminal embedding is
closest (paper §3.3). The planner only sees an objective; the dynamics backend decides what "predicted"
means (learned world model or simulator).

Chunk rules, the same for every dynamics backend:
* the first chunk runs open loop (paper §3.3 "Full-chunk deployment"), or is planned from a synthesised
  rest-state history with ``first_chunk="rest-history"`` (appendix A);
* the history a learned world model conditions on is anchored to the planning points: at boundary t it is
  the frames at t-(H_ctx-1)Δ, ..., t-Δ, t with the actions executed between them, whether or not Δ divides
  the chunk (paper Δ=5, H=16: frames t-10, t-5, t). ``wants_images`` asks for exactly those frames;
* a boundary whose history reaches before step 0 (only when (H_ctx-1)Δ exceeds the chunk) runs open loop
  and is counted in ``info()["open_loop_chunks"]``; so is a chunk the gate skipped (``gate_threshold``: the
  WAM's chunk, scored through the planning objective, is already close enough to its target), as "gated"; a
  chunk whose cost is above ``gate_above`` (the model's prediction far from the target, where its ranking is
  least trustworthy) as "gated-above";
  chunks searched whose plan was then not executed count as "rejected" (``accept_margin``: the plan's predicted
  gain was too small) or "rank-gated" (``rank_gate``: too few of the search's first random neighbours of the
  WAM's chunk scored below it, so the model sees the WAM's chunk as already among the best it can tell apart);
  a history frame that should exist but was never
  shown to the policy is a :class:`PlanningError`, never a silent open-loop chunk.

Receding horizon (``replan_every`` K, not in the paper): a planned chunk executes only its first K steps as
planned; at t+K, t+2K, ... the rest of it is searched again from the new observation toward the same target
(the WAM is not queried again: its target is the chunk's end), the remaining plan being the search's initial
mean. A learned model then predicts 16-K steps from a real frame instead of 16, and conditions on the history
anchored at the re-planning step; K must be a multiple of Δ that divides the chunk, so that the rest's rollout
ends at the target's step (the paper's Δ = 5 with 16-step chunks has no such K). The boundary's gates and tests
(gate_threshold, gate_above, accept_margin, rank_gate) decide whether a chunk is planned at all; its re-plans
then execute unconditionally. A chunk's ``search_s`` includes its re-plans; ``correction`` and the costs are
the boundary search's.

Bias correction (``bias_correction`` α, not in the paper; offset-free MPC's disturbance estimate): at boundary t
the learned model first predicts the frame it is now looking at, from the previous boundary's history under
the actions actually executed since; the error r = z(t) - ẑ(t) is its bias on the chunk just run. Every
candidate's predicted terminal embedding then gets α·r added before the cost, on the bet that the model's
error persists from one chunk to the next (a systematic offset of the cube near the mount, say). The chunk's
record keeps the bias (``bias``: mean square of r) and how well the previous chunk's bias would have predicted
it (``bias_left``: mean square of r - α·r_prev), the test of that bet. A boundary whose previous boundary's
history reaches before step 0 is not corrected (a rest-state history is synthetic, not the model's regime);
the gates compare corrected costs, and the measurement's rollout counts in ``search_s``. It needs a learned
model whose rollout ends at the boundary (Δ dividing H) and whole chunks (no ``replan_every``: a re-plan's
shorter rollout from a fresh frame has another error).

Warm start (``warm_start="residual"``): a plan covers at most the chunk it refines and the whole chunk is
executed, so "the previous plan shifted by H" is always empty here; what can carry over is the previous
chunk's correction (plan minus the WAM's chunk, step by step), added with ``warm_weight`` to the WAM's new
chunk on the arm dimensions, on the bet that the WAM's error persists from one chunk to the next.

Devices: the target embedding, the seed chunk and every candidate live on ``dynamics.device``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from wamplan.config import field, require, to_dict
from wamplan.envs.contract import CAMERAS, Observation
from wamplan.errors import UserError
from wamplan.planning.base import Planner
from wamplan.planning.costs import CostFn
from wamplan.planning.dynamics import Dynamics, LearnedDynamics, PlanningContext
from wamplan.policies.base import Policy
from wamplan.wam.base import WAM, WAMOutput


WARM_STARTS = ("none", "residual")
DISCARDED = ("rejected", "rank-gated")  # open-loop reasons of chunks that were searched, the plan then not executed


@dataclass(frozen=True)
class PlannedPolicyConfig:
    first_chunk: str = field("open-loop", "open-loop (paper) or rest-history: plan chunk 1 from a synthesised history")
    plan_seed: int = field(0, "base seed of the planner's sampling (plus the chunk index)")
    gate_threshold: float | None = field(
        None, "gated planning: execute the WAM's chunk without a search when its cost (the seed scored through "
        "the planning objective) is at most this; None = plan every chunk. Calibrate it with "
        "`wamplan gate-calibrate EVAL_DIR` on held-out episodes")
    gate_above: float | None = field(
        None, "out-of-range gate: execute the WAM's chunk without a search when its cost is ABOVE this: where the "
        "model's prediction is far from the WAM's target (e.g. in contact, at insertion) its ranking is least "
        "trustworthy. None = no upper gate. Calibrate it, like gate_threshold, with `wamplan gate-calibrate`")
    warm_start: str = field(
        "none", "initial search mean: none (the WAM's chunk, the paper) or residual (the WAM's chunk plus "
        "warm_weight times the previous planned chunk's correction, arm dimensions only)")
    warm_weight: float = field(0.5, "with warm_start=residual: the share of the previous correction carried over")
    disagreement_weight: float = field(
        0.0, "uncertainty-aware cost: add this times the ensemble's disagreement (variance across members) to "
        "the cost; needs an ensemble world model (several comma-separated checkpoints). 0 = off")
    accept_margin: float | None = field(
        None, "trust test: execute the plan only if the model predicts it lowers the WAM chunk's cost by at least "
        "this fraction (e.g. 0.1), else the WAM's chunk; a model that cannot tell close chunks apart then "
        "leaves the WAM alone instead of adding its noise. None = always execute the plan (the paper)")
    rank_gate: float | None = field(
        None, "rank test: execute the plan only if at least this share of the search's first random candidates "
        "(samples around its initial mean: the WAM's chunk, unless warm-started) score below that mean, i.e. the "
        "model sees it as no better than its neighbours; else the WAM's chunk (e.g. 0.5). None = always execute "
        "the plan (the paper)")
    bias_correction: float = field(
        0.0, "offset-free planning: add this share of the learned model's error on the chunk just executed (the "
        "observed frame minus the model's prediction of it from the previous boundary) to every candidate's "
        "predicted terminal embedding, e.g. 0.5; the gates then compare corrected costs. 0 = off (the paper)")
    replan_every: int | None = field(
        None, "receding horizon: execute this many steps of a planned chunk, then re-plan the rest of it from the "
        "new observation toward the same target (a multiple of the world model's frameskip that divides the "
        "chunk, e.g. 8 for the mini preset's 16-step chunks and frameskip 4; the paper preset's frameskip 5 has "
        "none). Re-plans are not gated or trust-tested. None = execute the whole chunk (the paper)")
    correction_gain: float = field(
        1.0, "execute the WAM's chunk plus this multiple of the planned correction (plan minus the WAM's chunk), "
        "clipped to the action bounds: below 1 damps it, above 1 extends it along the way the search went. A "
        "re-plan's is scaled around the plan it refines. 1 = execute the plan (the paper; on the mini task's "
        "validation seeds 0.3, 0.5, 1.5 and 2 all lost to it, stop 23)")

    def __post_init__(self):
        require(self.first_chunk in ("open-loop", "rest-history"),
                f"first_chunk must be open-loop or rest-history, got {self.first_chunk!r}")
        require(self.warm_start in WARM_STARTS, f"warm_start must be one of {WARM_STARTS}, got {self.warm_start!r}")
        require(0.0 <= self.warm_weight <= 1.0, f"warm_weight must be in [0, 1], got {self.warm_weight}")
        require(self.disagreement_weight >= 0, f"disagreement_weight must be >= 0, got {self.disagreement_weight}")
        require(self.accept_margin is None or 0.0 <= self.accept_margin < 1.0,
                f"accept_margin must be in [0, 1) or None, got {self.accept_margin}")
        require(self.gate_threshold is None or self.gate_above is None or self.gate_threshold < self.gate_above,
                f"gate_threshold ({self.gate_threshold}) must be below gate_above ({self.gate_above}): "
                "the search runs only for costs between the two")
        require(self.rank_gate is None or 0.0 < self.rank_gate <= 1.0,
                f"rank_gate must be in (0, 1] or None, got {self.rank_gate}")
        require(0.0 <= self.bias_correction <= 1.0, f"bias_correction must be in [0, 1], got {self.bias_correction}")
        require(self.replan_every is None or self.replan_every >= 1,
                f"replan_every must be >= 1 or None, got {self.replan_every}")
        require(0.0 < self.correction_gain <= 4.0, f"correction_gain must be in (0, 4], got {self.correction_gain} "
                "(1 executes the plan; for the WAM's own chunks, unplanned, run condition 1)")


class PlanningError(UserError):
    """The planned policy was driven in a way that leaves it without the history it needs."""


def check_replan_every(k: int, chunk: int, frameskip: int | None) -> None:
    """Refuse a re-planning period that does not fit: K must divide the ``chunk`` and be shorter than it, and be
    a multiple of a learned model's ``frameskip`` (None: the simulator, any K) so the rest's rollout ends at
    the target's step."""
    if not (k < chunk and chunk % k == 0):
        raise PlanningError(f"replan_every={k} must divide the WAM's {chunk}-step chunk and be shorter than "
                            f"it, e.g. {chunk // 2}; or drop it to execute whole chunks")
    if frameskip is not None and k % frameskip:
        raise PlanningError(f"replan_every={k} must be a multiple of the world model's frameskip "
                            f"{frameskip}, so that the rest's rollout ends at the target's step")


class PlannedPolicy(Policy):
    name = "planned"

    def __init__(self, wam: WAM, planner: Planner, dynamics: Dynamics, encoder, cost: CostFn, *,
                 target_wam: WAM | None = None, config: PlannedPolicyConfig | None = None,
                 instruction: str | None = None, world_models: tuple[str, ...] = ()):
        self.wam, self.target_wam = wam, target_wam or wam
        self.planner, self.dynamics, self.encoder, self.cost = planner, dynamics, encoder, cost
        self.config = config or PlannedPolicyConfig()
        self.world_models = tuple(world_models)  # the learned dynamics' checkpoints, for the record (config_dict)
        self.instruction = instruction or getattr(wam, "default_instruction", "")
        self.chunk = wam.chunk_length
        self.frameskip = getattr(dynamics, "frameskip", self.chunk)
        self.context = getattr(dynamics, "context", 1)
        self.period = self._replan_period()  # steps between planning points: the chunk, or replan_every
        if self.config.rank_gate is not None and not getattr(planner.config, "include_mean", False):
            raise PlanningError("rank_gate compares the WAM's chunk with the search's first samples, so the planner "
                                "must score it: drop --no-include-mean or the rank gate")
        if self.config.bias_correction > 0 and dynamics.needs_history:
            if dynamics.covered(self.chunk) != self.chunk:
                raise PlanningError(f"bias_correction compares the model's prediction with the frame at the next "
                                    f"boundary, but its frameskip {self.frameskip} does not divide the "
                                    f"{self.chunk}-step chunk; drop --bias-correction")
            if self.config.replan_every is not None:
                raise PlanningError("bias_correction measures the error of whole chunks; drop --replan-every or "
                                    "--bias-correction")
        if self.config.disagreement_weight > 0 and isinstance(dynamics, LearnedDynamics):
            raise PlanningError("disagreement_weight needs an ensemble of world models, got one; pass several "
                                "comma-separated checkpoints (e.g. --wm-augmented A,B,C) or set it to 0")
        self.reset()

    def _replan_period(self) -> int:
        k = self.config.replan_every
        if k is None:
            return self.chunk
        check_replan_every(k, self.chunk, self.frameskip if self.dynamics.needs_history else None)
        if getattr(self.planner.config, "num_optimized", None) is not None:
            raise PlanningError("replan_every re-plans the rest of a chunk, all of which the search optimises; "
                                "drop --num-optimized or --replan-every")
        return k

    @property
    def chunk_length(self) -> int:
        """H: the planned policy acts in the WAM's chunks (what ``collect --branches`` cuts at)."""
        return self.chunk

    @property
    def device(self) -> torch.device:
        """Where the search runs: the dynamics backend's device."""
        return self.dynamics.device

    # ------------------------------------------------------------------ Policy
    def reset(self, seed: int | None = None) -> None:
        self.wam.reset()
        if self.target_wam is not self.wam:
            self.target_wam.reset()
        self._queue: list[np.ndarray] = []
        self._frames: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}  # step -> (z (V, N, D), q (P,)) on device
        self._executed: list[np.ndarray] = []
        self.chunks: list[dict[str, Any]] = []
        self.last_plan = None
        self._correction: torch.Tensor | None = None  # (H_opt, A) last planned chunk minus its WAM seed
        self._replan: dict[str, Any] | None = None  # the planned chunk being executed: its target and record
        self._episode_seed = seed or 0
        self._bias: torch.Tensor | None = None  # (V, N, D) the model's error on the chunk before (bias_correction)

    def _history_steps(self, t: int) -> list[int]:
        """The steps of the history frames for the chunk boundary t, oldest first."""
        return [t - i * self.frameskip for i in range(self.context - 1, -1, -1)]

    def _is_history_step(self, step: int) -> bool:
        """Whether ``step`` is t - iΔ (0 <= i < H_ctx) for some planning point t >= step: a chunk boundary, or
        a re-planning step of the chunk being executed when it was planned (only such a chunk re-plans)."""
        period = self.period if self._replan is not None else self.chunk
        return any((step + i * self.frameskip) % period == 0 for i in range(self.context))

    def wants_images(self, step: int) -> bool:
        return step % self.chunk == 0 or (self.dynamics.needs_history and self._is_history_step(step))

    def act(self, obs: Observation) -> np.ndarray:
        t = obs.step
        if self.dynamics.needs_history and self._is_history_step(t):
            if obs.images is None:
                raise PlanningError(f"the planned policy needs the views at step {t} (a history frame) but "
                                    f"got none; drive it with run_episode or render when wants_images(t) is true")
            self._frames[t] = (self._encode(obs.images), torch.as_tensor(obs.proprio, device=self.device))
            oldest = t - (self.context - 1) * self.frameskip - self.chunk  # nothing older is needed again
            self._frames = {s: f for s, f in self._frames.items() if s >= oldest}
        if t % self.chunk == 0:
            self._replan = None
            self._queue = list(self._plan_chunk(obs))
        elif t % self.period == 0 and self._replan is not None:
            self._queue = list(self._replan_rest(obs))
        a = self._queue.pop(0)
        self._executed.append(np.clip(a, -1, 1))
        return a

    def info(self) -> dict[str, Any]:
        keys = ("wam_s", "target_encode_s", "search_s")
        planned = [c for c in self.chunks if c["planned"]]
        open_loop: dict[str, int] = {}
        for c in self.chunks:
            if not c["planned"]:
                open_loop[c["open_loop"]] = open_loop.get(c["open_loop"], 0) + 1
        return dict(chunks=self.chunks, planned_chunks=len(planned), open_loop_chunks=open_loop,
                    replans=sum(len(c.get("replans", ())) for c in self.chunks),
                    mean_s={k: float(np.mean([c[k] for c in planned])) for k in keys} if planned else {})

    def config_dict(self) -> dict[str, Any]:
        return dict(name=self.name, wam=self.wam.config_dict(), target_wam=self.target_wam.config_dict(),
                    planner=type(self.planner).__name__, planner_config=to_dict(self.planner.config),
                    dynamics=type(self.dynamics).__name__, world_models=list(self.world_models),
                    encoder=self.encoder.config_dict(), **to_dict(self.config))

    # ------------------------------------------------------------------ internals
    @torch.inference_mode()
    def _encode(self, images: dict[str, np.ndarray]) -> torch.Tensor:
        """camera -> (H, W, 3) uint8 views -> (V, N, D) float32 on the search's device."""
        x = torch.from_numpy(np.stack([images[c] for c in CAMERAS]))  # (V, H, W, 3)
        return self.encoder.encode(x.to(self.encoder.device)).float().to(self.device)  # (V, N, D)

    def _context(self, t: int) -> PlanningContext | None:
        """History frames at t-(Tc-1)Δ .. t and the action blocks between them; None before enough steps exist
        (then the chunk runs open loop), or a rest-state history with ``first_chunk="rest-history"``."""
        steps = self._history_steps(t)
        rest = self.config.first_chunk == "rest-history"
        if steps[0] < 0 and not rest:
            return None
        missing = [s for s in steps if s >= 0 and s not in self._frames]
        if missing:
            raise PlanningError(f"history frames at steps {missing} are missing for the chunk at step {t}; the "
                                f"policy must see every step from the episode start (reset it before each episode)")
        # Before step 0 the robot rested: the first frame again, with hold-still actions (arm still, gripper open).
        hold = np.zeros(5, np.float32)
        hold[4] = 1.0
        z = torch.stack([self._frames[max(s, 0)][0] for s in steps])  # (Tc, V, N, D)
        q = torch.stack([self._frames[max(s, 0)][1] for s in steps])  # (Tc, P)
        acts = np.stack([self._executed[s] if s >= 0 else hold for s in range(steps[0], t)])  # ((Tc-1)Δ, A)
        a = torch.from_numpy(acts.reshape(self.context - 1, -1).astype(np.float32)).to(self.device)  # (Tc-1, Δ·A)
        return PlanningContext(z, q, a)

    def _plan_chunk(self, obs: Observation) -> np.ndarray:
        t0 = time.perf_counter()
        seed_out: WAMOutput = self.wam.predict(obs, self.instruction)
        rec: dict[str, Any] = dict(step=obs.step, planned=False, wam_s=time.perf_counter() - t0,
                                   target_encode_s=0.0, search_s=0.0)
        self.chunks.append(rec)
        context = None
        if obs.step == 0 and self.config.first_chunk == "open-loop":
            rec["open_loop"] = "first-chunk"  # the paper's rule, for every dynamics backend
            return seed_out.actions
        if self.dynamics.needs_history:
            context = self._context(obs.step)
            if context is None:
                rec["open_loop"] = "warm-up"  # the history reaches before step 0
                return seed_out.actions
        if self.config.warm_start != "none":
            correction, self._correction = self._correction, None  # only a chunk planned just before carries over
        t1 = time.perf_counter()
        target_out = seed_out if self.target_wam is self.wam else self.target_wam.predict(obs, self.instruction)
        t2 = time.perf_counter()
        target = self._encode(target_out.images)  # (V, N, D) on the search's device
        t3 = time.perf_counter()
        bias = self._measure_bias(obs.step, rec) if self.config.bias_correction > 0 else None
        self.dynamics.prepare(context)
        covered = self.dynamics.covered(self.chunk)
        seed = torch.as_tensor(seed_out.actions, device=self.device)[:covered]  # (H_opt, A)
        objective = self.objective(target, bias)
        rec.update(wam_s=rec["wam_s"] + t2 - t1, target_encode_s=t3 - t2)
        init, wam_cost = seed, None
        if self.config.gate_threshold is not None or self.config.gate_above is not None or \
                self.config.warm_start != "none" or self.config.accept_margin is not None:
            wam_cost = float(objective(self._clip(seed)[None])[0])  # the WAM's own chunk, scored as the planner would
        if self.config.gate_threshold is not None and wam_cost <= self.config.gate_threshold:
            rec.update(open_loop="gated", seed_cost=wam_cost, search_s=time.perf_counter() - t3)
            return seed_out.actions
        if self.config.gate_above is not None and wam_cost > self.config.gate_above:
            rec.update(open_loop="gated-above", seed_cost=wam_cost, search_s=time.perf_counter() - t3)
            return seed_out.actions
        if self.config.warm_start == "residual" and correction is not None:
            init = seed.clone()  # (H_opt, A)
            init[:, :-1] += self.config.warm_weight * correction[:, :-1]  # arm only: the gripper stays the WAM's
        result = self.planner.plan(init, objective, seed=self.config.plan_seed + self._episode_seed * 1000 + obs.step)
        planned = self._damped(result.actions[:covered], seed)  # (H_opt, A) what is executed of the plan
        if self.config.warm_start != "none":
            self._correction = planned.float() - seed.float()  # (H_opt, A)
        plan = np.concatenate([planned.cpu().numpy(), seed_out.actions[covered:]]).astype(np.float32)  # (H, A)
        init_cost = float(result.seed_cost) if result.seed_cost is not None else float("nan")
        rec.update(planned=True, seed_cost=init_cost if wam_cost is None else wam_cost, best_cost=float(result.best_cost),
                   seed_rank=result.seed_rank,  # what planning changed: plan minus the WAM's chunk, mean per action dim
                   correction=[round(float(v), 4) for v in (plan[:covered] - seed_out.actions[:covered]).mean(0)])
        if init is not seed:
            rec["init_cost"] = init_cost  # the warm-started initial mean's cost
        self.last_plan = result
        if self.config.rank_gate is not None and not result.seed_rank >= self.config.rank_gate:  # NaN: no rank, keep
            rec.update(planned=False, open_loop="rank-gated", search_s=time.perf_counter() - t3)
            self._correction = None  # the WAM's chunk ran: nothing of this plan carries over
            return seed_out.actions
        if self.config.accept_margin is not None:
            plan_cost = float(objective(self._clip(planned)[None])[0])  # what would be executed
            rec["plan_cost"] = plan_cost
            if plan_cost > (1.0 - self.config.accept_margin) * wam_cost:  # not clearly better: keep the WAM's
                rec.update(planned=False, open_loop="rejected", search_s=time.perf_counter() - t3)
                self._correction = None  # the WAM's chunk ran: nothing of this plan carries over
                return seed_out.actions
        rec["search_s"] = time.perf_counter() - t3
        if self.period < self.chunk:
            self._replan = dict(objective=objective, rec=rec, seed=seed_out.actions)
            rec["replans"] = []
        return plan

    def _replan_rest(self, obs: Observation) -> np.ndarray:
        """At a re-planning step inside a planned chunk: search the rest of it again from this observation,
        toward the chunk's target, starting from the rest of the current plan. -> (R, A) the actions to run."""
        t0 = time.perf_counter()
        rest = np.stack(self._queue)  # (R, A) what the plan would still execute
        # a planned chunk had its history at its boundary, so the later frames of this one exist too
        self.dynamics.prepare(self._context(obs.step) if self.dynamics.needs_history else None)
        covered = self.dynamics.covered(len(rest))
        init = torch.as_tensor(rest[:covered], device=self.device)  # (R_opt, A)
        result = self.planner.plan(init, self._replan["objective"],
                                   seed=self.config.plan_seed + self._episode_seed * 1000 + obs.step)
        planned = self._damped(result.actions[:covered], init)  # (R_opt, A)
        plan = np.concatenate([planned.cpu().numpy(), rest[covered:]]).astype(np.float32)  # (R, A)
        offset = obs.step % self.chunk
        if self._correction is not None:  # the chunk's executed correction now ends with this re-plan
            seed = torch.as_tensor(self._replan["seed"][offset:offset + covered], device=self.device)
            self._correction[offset:offset + covered] = planned.float() - seed.float()
        self.last_plan = result
        dt = time.perf_counter() - t0
        rec = self._replan["rec"]
        rec["replans"].append(dict(step=obs.step, seed_cost=float(result.seed_cost), best_cost=float(result.best_cost),
                                   search_s=dt))
        rec["search_s"] += dt  # a chunk's search time includes its re-plans
        return plan

    def objective(self, target: torch.Tensor, bias: torch.Tensor | None = None):
        """candidates (B, H_opt, A) -> costs (B,): the cost of the dynamics' prediction (plus ``bias_correction``
        times ``bias`` (V, N, D), when given) against ``target`` (V, N, D), plus ``disagreement_weight`` times
        the ensemble's disagreement."""
        w = self.config.disagreement_weight
        shift = None if bias is None else self.config.bias_correction * bias  # (V, N, D)

        def objective(cands: torch.Tensor) -> torch.Tensor:
            if w == 0:
                z, spread = self.dynamics.terminal(cands), None  # (B, V, N, D)
            else:
                z, spread = self.dynamics.predict(cands)  # (B, V, N, D), (B,)
            c = self.cost(z if shift is None else z.float() + shift, target)  # (B,)
            return c if spread is None else c + w * spread.to(self.device)

        return objective

    def _measure_bias(self, t: int, rec: dict[str, Any]) -> torch.Tensor | None:
        """The learned model's error on the chunk that ended at boundary t: the frame seen at t minus its
        prediction from the previous boundary's history under the executed actions -> (V, N, D), or None where
        it cannot be measured. Leaves the dynamics prepared at t - H (the caller prepares it again)."""
        prev, bias_prev = t - self.chunk, self._bias
        self._bias = None
        if not self.dynamics.needs_history or self._history_steps(prev)[0] < 0:
            return None  # the simulator has no bias; a history before step 0 is not a real one
        context = self._context(prev)
        acts = torch.from_numpy(np.stack(self._executed[prev:t]).astype(np.float32)).to(self.device)  # (H, A)
        self.dynamics.prepare(context)
        self._bias = self._frames[t][0] - self.dynamics.terminal(acts[None])[0].float()  # (V, N, D)
        rec["bias"] = float(self._bias.square().mean())
        if bias_prev is not None:  # would the chunk before's bias have predicted this one's?
            rec["bias_left"] = float((self._bias - self.config.bias_correction * bias_prev).square().mean())
        return self._bias

    def _damped(self, actions: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
        """(L, A) planned actions -> (L, A): ``ref`` (the WAM's chunk, or the plan a re-plan refines) plus
        ``correction_gain`` times the planned change, clipped to the planner's bounds; the plan itself at gain 1."""
        g = self.config.correction_gain
        if g == 1.0:
            return actions
        ref = ref.to(actions)  # (L, A)
        return self._clip(ref + g * (actions - ref)).to(actions)

    def _clip(self, actions: torch.Tensor) -> torch.Tensor:
        """The seed as a planner scores it: clipped to the planner's action bounds."""
        lo, hi = getattr(self.planner.config, "action_low", -1.0), getattr(self.planner.config, "action_high", 1.0)
        return actions.float().clamp(lo, hi)
