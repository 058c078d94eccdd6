"""The planned policy: a WAM whose every chunk is refined by planning toward its own predicted images.

At a chunk boundary t, :meth:`PlannedPolicy.plan_chunk` queries the *seed* WAM for its chunk and the *target*
WAM for its predicted t+H views (the same WAM unless an evaluation condition swaps in the expert oracle),
encodes the target views, and lets the planner search for the chunk whose predicted terminal embedding is
closest (paper §3.3). The planner only sees an objective; the dynamics backend decides what "predicted" means
(learned world model or simulator); a learned model's history is kept by
:class:`~wamplan.planning.history.FrameHistory`. The settings, and what each needs, are
:class:`~wamplan.planning.policy_config.PlannedPolicyConfig`'s.

Contract, the same for every dynamics backend:

* the first chunk runs open loop (paper §3.3, "first-chunk"), or is planned from a synthesised rest-state
  history with ``first_chunk="rest-history"`` (appendix A); a later boundary whose history reaches before
  step 0 runs open loop too ("warm-up");
* the :class:`~wamplan.planning.gates.Gates` may run the WAM's chunk instead of a plan, without a search
  ("gated") or after it ("rejected");
* with ``requery_every`` K < H the WAM is queried and its chunk planned every K steps, and the first K actions of
  each planned chunk run (a robot that runs part of each chunk; the reference the planning proxy follows);
* each boundary's :class:`ChunkDecision` says what runs and why; ``info()["chunks"]`` keeps its record and
  ``info()["open_loop_chunks"]`` counts the open-loop reasons;
* a history frame that should exist but was never shown to the policy is a :class:`PlanningError`.

Devices: the target embedding, the seed chunk and every candidate live on ``dynamics.device``.

The task is the WAM's (``wam.task``): its views are encoded in the order of the dynamics' ``cameras`` (the world
model's, else the task's), its arm entries carry a warm start, its rest action fills a rest-state history, and
the planner's task settings are filled from it (``Planner.for_task``). The target WAM and the dynamics (the
world model's checkpoint, or the simulator's env) must have been made for the same task: one line otherwise.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np
import torch

from wamplan.config import to_dict
from wamplan.envs.spec import Observation, check_same_task, require_images, require_observation
from wamplan.planning.base import Planner
from wamplan.planning.costs import CostFn
from wamplan.planning.decision import ChunkCosts, ChunkDecision, ChunkTimings
from wamplan.planning.dynamics import Dynamics, PlanningContext, task_name
from wamplan.planning.history import FrameHistory
from wamplan.planning.policy_config import PlannedPolicyConfig, PlanningError, check_fits
from wamplan.policies.base import Policy
from wamplan.wam.base import WAM, WAMOutput

__all__ = ["PlannedPolicy", "PlannedPolicyConfig"]  # the policy and its config, which most callers import with it


class PlannedPolicy(Policy):
    """``wam`` whose chunks ``planner`` refines in ``dynamics``, scoring predictions with ``cost`` against the
    target views encoded by ``encoder``; see the module docstring for the chunk rules."""

    name = "planned"

    def __init__(self, wam: WAM, planner: Planner, dynamics: Dynamics, encoder, cost: CostFn, *,
                 target_wam: WAM | None = None, config: PlannedPolicyConfig | None = None,
                 instruction: str | None = None, world_models: tuple[str, ...] = ()):
        self.wam, self.target_wam = wam, target_wam or wam
        self.task = wam.task
        check_same_task(self.task.name, task_name(self.target_wam), f"WAM {self.target_wam.name} (the target)",
                        f"aim with a WAM made for '{self.task.name}', the planned WAM's task")
        check_same_task(self.task.name, task_name(dynamics),
                        "checkpoint of the world model" if dynamics.needs_history else "simulator env",
                        f"plan in {'a world model' if dynamics.needs_history else 'an env'} made for "
                        f"'{self.task.name}', the WAM's task")
        self.planner = planner.for_task(self.task)
        self.dynamics, self.encoder, self.cost = dynamics, encoder, cost
        self.cameras = dynamics.cameras or self.task.cameras  # the order the encoded views are stacked in
        self._arm = list(self.task.arm)  # the action entries a warm start carries over
        self.config = config or PlannedPolicyConfig()
        self.gates = self.config.gates
        self.world_models = tuple(world_models)  # the learned dynamics' checkpoints, for the record (config_dict)
        self.instruction = instruction or getattr(wam, "default_instruction", "")
        self.chunk = wam.chunk_length
        check_fits(self.config, self.chunk, dynamics)
        self.period = self.config.requery_every or self.chunk  # K: steps between the WAM's queries
        self.history = FrameHistory.for_dynamics(dynamics, self.chunk, self.encode, self.task.hold_action,
                                                 rest_state=self.config.first_chunk == "rest-history",
                                                 period=self.period, imagined=self.config.history == "imagined")
        self.reset()

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
        self.wam.begin_episode(seed)
        if self.target_wam is not self.wam:
            self.target_wam.begin_episode(seed)
        self.history.reset()
        self._queue: list[np.ndarray] = []  # (A,) the actions still to run of the current chunk
        self.chunks: list[dict[str, Any]] = []  # one record a chunk (ChunkDecision.record)
        self.last_plan = None  # the latest PlanResult
        self.last_decision: ChunkDecision | None = None
        self._correction: tuple[int, torch.Tensor] | None = None  # (its step, (H_opt, A) plan minus its WAM seed)
        self._episode_seed = seed or 0

    def wants_images(self, step: int) -> bool:
        return (step % self.period == 0 or any(step % self.period in w.frame_offsets for w in self._wams())
                or self.history.wants(step))

    def _wams(self) -> tuple[WAM, ...]:
        """The WAM and, where it is another, the target's WAM: each gets the in-chunk frames it asks for."""
        return (self.wam,) if self.target_wam is self.wam else (self.wam, self.target_wam)

    def act(self, obs: Observation) -> np.ndarray:
        require_observation(obs, "PlannedPolicy.act")
        t = obs.step
        self.history.observe(obs)
        for w in self._wams():
            if t % self.period in w.frame_offsets:
                w.observe(obs)
        if t % self.period == 0:
            self._queue = list(self.plan_chunk(obs).executed)
        a = self._queue.pop(0)
        self.history.record_action(a)
        return a

    def info(self) -> dict[str, Any]:
        keys = ("wam_s", "target_encode_s", "search_s")
        planned = [c for c in self.chunks if c["planned"]]
        open_loop: dict[str, int] = {}
        for c in self.chunks:
            if not c["planned"]:
                open_loop[c["open_loop"]] = open_loop.get(c["open_loop"], 0) + 1
        return dict(chunks=self.chunks, planned_chunks=len(planned), open_loop_chunks=open_loop,
                    mean_s={k: float(np.mean([c[k] for c in planned])) for k in keys} if planned else {})

    def config_dict(self) -> dict[str, Any]:
        return dict(name=self.name, wam=self.wam.config_dict(), target_wam=self.target_wam.config_dict(),
                    planner=type(self.planner).__name__, planner_config=to_dict(self.planner.config),
                    dynamics=type(self.dynamics).__name__, world_models=list(self.world_models),
                    encoder=self.encoder.config_dict(), **to_dict(self.config))

    # ------------------------------------------------------------------ the chunk loop
    def plan_chunk(self, obs: Observation) -> ChunkDecision:
        """Decide the chunk that starts at ``obs.step`` (a chunk boundary, with images): query the WAM, then plan
        its chunk or run it open loop. The frame of ``obs`` joins the history, the decision joins ``chunks``
        (its record) and becomes ``last_decision``. Call it once per boundary (every ``period`` steps), in step
        order after ``reset`` (``act`` does); between boundaries, ``act`` must see every step."""
        require_observation(obs, "PlannedPolicy.plan_chunk")
        require_images(obs, self.cameras, "PlannedPolicy.plan_chunk")
        t = obs.step
        if t % self.period:
            raise PlanningError(f"plan_chunk plans at chunk boundaries (steps 0, {self.period}, "
                                f"{2 * self.period}, ...), got step {t}; use act() between boundaries")
        self.history.observe(obs)
        t0 = time.perf_counter()
        seed_out: WAMOutput = self.wam.predict(obs, self.instruction)
        wam_s = time.perf_counter() - t0
        rule = self.open_loop_rule(t)
        if rule is not None:
            return self._record(ChunkDecision(t, seed_out.actions, seed_out.actions, rule,
                                              timings=ChunkTimings(wam_s=wam_s)))
        context = self.history.planning_context(t) if self.dynamics.needs_history else None
        return self._search(obs, seed_out, context, wam_s)

    def open_loop_rule(self, t: int) -> str | None:
        """Why the chunk at boundary t runs open loop whatever the WAM proposes: "first-chunk" (the paper's rule,
        for every backend), "warm-up" (a learned model's history reaches before step 0), or None (it is planned,
        unless a gate decides otherwise)."""
        if t == 0 and self.config.first_chunk == "open-loop":
            return "first-chunk"
        if self.dynamics.needs_history and not self.history.real(t) and not self.history.rest_state:
            return "warm-up"
        return None

    def _record(self, decision: ChunkDecision) -> ChunkDecision:
        """Keep ``decision`` as the last one and its record in ``chunks`` -> the decision."""
        self.chunks.append(decision.record())
        self.last_decision = decision
        return decision

    def _search(self, obs: Observation, seed_out: WAMOutput, context: PlanningContext | None,
                wam_s: float) -> ChunkDecision:
        """Plan a chunk whose history exists: encode the target, ask the gate whether to search, set the initial
        mean, search, decide between the plan and the WAM's chunk, record the decision."""
        carried, self._correction = self._correction, None  # only the chunk planned just before, run whole, carries
        carried = carried[1] if carried is not None and carried[0] == obs.step - self.chunk else None  # over
        target, query_s, encode_s = self._encode_target(obs, seed_out)  # (V, N, D)
        started = time.perf_counter()  # the chunk's search_s: from here to its decision
        self.dynamics.prepare(context)
        objective = self.objective(target)
        seed = torch.as_tensor(seed_out.actions, device=self.device)[:self.dynamics.covered(self.chunk)]  # (H_opt, A)
        wam_cost = self._wam_cost(objective, seed)
        skip = self.gates.before_search(wam_cost)
        if skip is not None:
            decision = ChunkDecision(obs.step, seed_out.actions, seed_out.actions, skip, target=target,
                                     costs=ChunkCosts(seed=wam_cost))
        else:
            init = self._initial_mean(seed, carried)  # (H_opt, A)
            self.last_plan = self.planner.plan(init, objective, seed=self._plan_seed(obs.step))
            decision = self._decide(obs.step, seed_out.actions, seed, init, objective, wam_cost, target)
        timings = ChunkTimings(wam_s + query_s, encode_s, time.perf_counter() - started)
        return self._record(dataclasses.replace(decision, timings=timings))

    def _encode_target(self, obs: Observation, seed_out: WAMOutput) -> tuple[torch.Tensor, float, float]:
        """The target WAM's predicted views at t+H (the seed WAM's own, unless another WAM aims), encoded ->
        ((V, N, D) on the search's device, seconds querying the target WAM, seconds encoding)."""
        t0 = time.perf_counter()
        target_out = seed_out if self.target_wam is self.wam else self.target_wam.predict(obs, self.instruction)
        t1 = time.perf_counter()
        target = self.encode(target_out.images)  # (V, N, D)
        return target, t1 - t0, time.perf_counter() - t1

    def _wam_cost(self, objective, seed: torch.Tensor) -> float | None:
        """The WAM's own chunk (H_opt, A), scored as the planner would, where a gate or the warm start reads it;
        else None (not scored)."""
        if not (self.gates.needs_wam_cost or self.config.warm_start != "none"):
            return None
        return float(objective(self.clip(seed)[None])[0])

    def _initial_mean(self, seed: torch.Tensor, carried: torch.Tensor | None) -> torch.Tensor:
        """The search's initial mean (H_opt, A): the WAM's chunk ``seed``, plus with ``warm_start="residual"``
        ``warm_weight`` times the ``carried`` correction of the chunk planned just before (arm entries only)."""
        if self.config.warm_start != "residual" or carried is None:
            return seed
        init = seed.clone()  # (H_opt, A)
        init[:, self._arm] += self.config.warm_weight * carried[:, self._arm]  # the gripper stays the WAM's
        return init

    def _decide(self, step: int, seed_actions: np.ndarray, seed: torch.Tensor, init: torch.Tensor, objective,
                wam_cost: float | None, target: torch.Tensor) -> ChunkDecision:
        """The plan of the search just run (``last_plan``) against the WAM's chunk ``seed_actions`` (H, A), whose
        first H_opt steps ``seed`` the search covered: the accept gate's verdict, the costs and the correction
        carried to the next chunk's search (warm start) -> the decision (its timings left to the caller)."""
        result, covered = self.last_plan, seed.shape[0]
        planned = result.actions[:covered]  # (H_opt, A) what is executed of the plan
        plan = np.concatenate([planned.cpu().numpy(), seed_actions[covered:]]).astype(np.float32)  # (H, A)
        reason, plan_cost = self.gates.after_search(wam_cost, lambda: float(objective(self.clip(planned)[None])[0]))
        if reason is None and self.config.warm_start != "none":
            self._correction = (step, planned.float() - seed.float())  # (H_opt, A) the correction the next search carries
        init_cost = float(result.seed_cost)  # NaN without include_mean
        costs = ChunkCosts(seed=init_cost if wam_cost is None else wam_cost, best=float(result.best_cost),
                           plan=plan_cost, init=None if init is seed else init_cost)
        change = (plan[:covered] - seed_actions[:covered]).mean(0)  # (A,) what planning changed, per action dim
        return ChunkDecision(step, seed_actions, seed_actions if reason else plan, reason, target=target, plan=plan,
                             costs=costs, seed_rank=result.seed_rank,
                             correction=tuple(round(float(v), 4) for v in change))

    # ------------------------------------------------------------------ scoring
    def objective(self, target: torch.Tensor):
        """candidates (B, H_opt, A) -> costs (B,): the cost of the dynamics' prediction against ``target``
        (V, N, D)."""

        def objective(cands: torch.Tensor) -> torch.Tensor:
            return self.cost(self.dynamics.terminal(cands), target)  # (B, V, N, D) -> (B,)

        return objective

    @torch.inference_mode()
    def encode(self, images: dict[str, np.ndarray]) -> torch.Tensor:
        """camera -> (H, W, 3) uint8 views -> (V, N, D) float32 on the search's device."""
        x = torch.from_numpy(np.stack([images[c] for c in self.cameras]))  # (V, H, W, 3)
        return self.encoder.encode(x.to(self.encoder.device)).float().to(self.device)  # (V, N, D)

    def clip(self, actions: torch.Tensor) -> torch.Tensor:
        """(..., A) actions as the planner scores them: float, clipped to its action bounds."""
        lo, hi = getattr(self.planner.config, "action_low", -1.0), getattr(self.planner.config, "action_high", 1.0)
        return actions.float().clamp(lo, hi)

    def _plan_seed(self, step: int) -> int:
        """The planner's random seed for a search at ``step`` of this episode: reproducible per episode and step."""
        return self.config.plan_seed + self._episode_seed * 1000 + step
