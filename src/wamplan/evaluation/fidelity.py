"""Planning fidelity: does a learned world model rank candidate chunks the way the simulator does?

At the real chunk boundaries (after the first, which every condition runs open loop) of a WAM episode run
open loop in the live env, the SAME N candidates — the WAM's own chunk (candidate 0) and N-1 Gaussian
samples around it at ``sigma``, clipped to [-1, 1], drawn from a generator seeded by (seed, episode, step) —
are scored toward the WAM's own predicted views

* in each learned world model, with the real history (exactly as :class:`PlannedPolicy` builds it: each
  model drives its own ``PlannedPolicy`` whose planner only scores the fixed candidates and returns the
  WAM's chunk), and
* in the simulator (``SimulatorDynamics`` with that model's own encoder and the same target), the
  "true" cost.

Then the WAM's own chunk is executed, so the episode stays open loop (unless ``execute``). Per model and boundary:
Spearman rank correlation of the two cost vectors, overlap of the two top-k sets, whether the model's
pick beats the WAM's chunk in the simulator (and how often a random sample does), the true-cost change
of the model's pick and of the simulator's own best candidate, relative to the WAM's chunk, and the
spread (std/mean) of the true costs. With ``task_metric``, every candidate is also stepped (state only) to
record the cube's xy distance to the hole axis after it: whether the true cost itself prefers chunks that
align the cube (Spearman of true cost against that distance, at boundaries where the cube is lifted), and
how far the model's pick moves the cube relative to the WAM's chunk; a task that does not measure the
cube's xy error (:data:`TASK_METRIC` among its metrics) is scored without it.

With ``plan``, each model also runs its own search (the evaluation's default planner, as condition 7 plans) at
every scored boundary, and the simulator scores that plan too: its true-cost gain over the WAM's chunk, in the
model's encoder's cost and in the first model's (one yardstick across encoders), and the cube's xy change. With
``execute`` = a model's label, the episode runs that model's plans instead of the WAM's chunks, to the episode's
end: the boundaries are then the states its own closed loop reaches, and ``episodes`` records its outcomes.

One WAM query per boundary feeds every policy (:class:`OnceWAM`), so a stochastic WAM cannot give the
models different chunks or targets. Scoring in the simulator restores the boundary snapshot afterwards;
a restored state differs from a never-restored one by ~1e-3 m (PhysX hidden state), so the episode may
drift slightly from a pure open-loop run of the same seed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import torch

from wamplan.config import check_numbers, field, require
from wamplan.planning.base import IterationStats, Planner, PlanResult, candidate_noise, make_planner
from wamplan.planning.costs import CostFn, make_cost
from wamplan.planning.defaults import DEFAULT_PLANNER
from wamplan.planning.dynamics import Dynamics, SimulatorDynamics
from wamplan.planning.policy import PlannedPolicy
from wamplan.planning.policy_config import PlannedPolicyConfig
from wamplan.envs.spec import Observation
from wamplan.policies.base import Policy
from wamplan.wam.once import OnceWAM
from wamplan.wam.base import WAM

TASK_METRIC = "cube_xy_error"  # the task metric task_metric needs: the cube task's (its privileged cube and hole)


@dataclass(frozen=True)
class FidelityConfig:
    num_candidates: int = field(32, "candidates per boundary: the WAM's chunk + N-1 Gaussian samples")
    sigma: float = field(0.10, "std of the samples around the WAM's chunk (normalised action units)")
    top_k: int = field(8, "size of the top sets whose overlap is reported (chance = k/N)")
    boundaries: tuple[int, ...] = field((1, 2, 3, 4), "chunk boundaries to score, as chunk indices (1 = step H; "
                                        "0, the first chunk, always runs open loop); the episode stops after the last")
    seed: int = field(0, "base seed of the candidate samples")
    task_metric: bool = field(True, "also step every candidate without rendering (~2 s a boundary) and record the "
                                    "cube's xy distance to the hole axis after it (mm): what alignment needs")
    plan: bool = field(False, "also run each model's own search (the evaluation's default planner) at every scored "
                              "boundary and score its plan in the simulator: what planning in the model gains there")
    execute: str = field("", "label of the model whose plans the episode executes, so the boundaries are the states "
                             "its own closed loop (condition 7) reaches (its executed plans are scored as with "
                             "plan); '' runs the WAM's chunks open loop")

    def __post_init__(self):
        check_numbers(self)
        require(self.num_candidates >= 2, f"num_candidates must be >= 2, got {self.num_candidates}")
        require(self.sigma > 0, f"sigma must be > 0, got {self.sigma}")
        require(1 <= self.top_k <= self.num_candidates,
                f"top_k must be in [1, num_candidates={self.num_candidates}], got {self.top_k}")
        require(len(self.boundaries) > 0 and min(self.boundaries) >= 1,
                f"boundaries must be chunk indices >= 1 (chunk 0 runs open loop), got {self.boundaries}")


def ranks(x: torch.Tensor) -> torch.Tensor:
    """(n,) values -> (n,) float64 ranks 1..n, ties given their average rank."""
    x = x.double()
    order = torch.argsort(x, stable=True)
    r = torch.empty_like(x)
    r[order] = torch.arange(1, len(x) + 1, dtype=torch.float64)
    for v in torch.unique(x):  # average the ranks of ties (few values tie in practice)
        same = x == v
        if same.sum() > 1:
            r[same] = r[same].mean()
    return r


def spearman(a: torch.Tensor, b: torch.Tensor) -> float:
    """Spearman rank correlation of two (n,) vectors; NaN if either is constant."""
    ra, rb = ranks(a), ranks(b)
    ra, rb = ra - ra.mean(), rb - rb.mean()
    den = float(ra.norm() * rb.norm())
    return float((ra @ rb) / den) if den > 0 else float("nan")


def top_overlap(a: torch.Tensor, b: torch.Tensor, k: int) -> float:
    """|lowest-k of a ∩ lowest-k of b| / k."""
    ia = set(torch.argsort(a.double(), stable=True)[:k].tolist())
    ib = set(torch.argsort(b.double(), stable=True)[:k].tolist())
    return len(ia & ib) / k


def cost_slope(costs: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
    """Least-squares slope (d,) of costs (N,) against the candidates' end-point shifts (N, d) (an intercept fitted)."""
    x = torch.cat([torch.ones_like(shift[:, :1]), shift], dim=1).double()  # (N, 1 + d)
    return torch.linalg.lstsq(x, costs.double()[:, None]).solution[1:, 0]  # (d,)


def slope_cosine(model: torch.Tensor, true: torch.Tensor, shift: torch.Tensor) -> float:
    """Cosine between the model's and the simulator's cost slopes over the end-point shifts (N, d): whether the
    model knows which way moving the chunk's end lowers the cost, even where its argmin is noise. NaN when the
    N candidates cannot determine d slopes and an intercept (N <= d + 1)."""
    if shift.shape[0] <= shift.shape[1] + 1:
        return float("nan")
    a, b = cost_slope(model, shift), cost_slope(true, shift)
    den = float(a.norm() * b.norm())
    return float(a @ b) / den if den > 0 else float("nan")


def boundary_stats(model: torch.Tensor, true: torch.Tensor, k: int, shift: torch.Tensor | None = None
                   ) -> dict[str, float]:
    """Compare the model's costs (N,) with the simulator's (N,) for one boundary; candidate 0 = the WAM's chunk.
    ``shift`` (N, d): each candidate's summed deviation from the WAM's chunk on the arm dimensions (its end
    point under delta control), for the slope agreement."""
    true = true.double()
    pick = int(torch.argmin(model.double()))
    return dict(spearman=spearman(model, true), top_overlap=top_overlap(model, true, k),
                slope_cosine=slope_cosine(model, true, shift) if shift is not None else float("nan"),
                pick_beats_wam=float(true[pick] < true[0]),
                random_beats_wam=float((true[1:] < true[0]).double().mean()),
                pick_gain=float((true[0] - true[pick]) / true[0]),  # > 0: the pick lowers the true cost
                best_gain=float((true[0] - true.min()) / true[0]),  # the simulator's own best candidate
                true_spread=float(true.std(correction=0) / true.mean()), pick=pick)


def plan_stats(plan: torch.Tensor, wam: torch.Tensor, plan_ref: torch.Tensor, wam_ref: torch.Tensor
               ) -> dict[str, float]:
    """A model's own plan against the WAM's chunk, both scored in the simulator: in the model's encoder's cost
    (``plan``, ``wam``) and in the first model's (``*_ref``), one yardstick for models of different encoders."""
    return dict(plan_gain=float((wam - plan) / wam), plan_beats_wam=float(plan < wam),
                plan_gain_ref=float((wam_ref - plan_ref) / wam_ref))


def task_stats(model: torch.Tensor, true: torch.Tensor, xy: torch.Tensor) -> dict[str, float]:
    """Costs (N,), (N,) against the cube's xy distance to the hole after each candidate, xy (N,) mm."""
    pick, sim_pick = int(torch.argmin(model.double())), int(torch.argmin(true.double()))
    return dict(true_vs_xy=spearman(true, xy), model_vs_xy=spearman(model, xy),
                pick_xy_change_mm=float(xy[pick] - xy[0]), sim_pick_xy_change_mm=float(xy[sim_pick] - xy[0]),
                best_xy_change_mm=float(xy.min() - xy[0]))


class _Scorer:
    """A 'planner' that scores the fixed candidates it is given (their first L actions) and returns the chunk the
    driver executes: the seed (the WAM's chunk), ``execute`` when the driver set one, or with ``own`` its own
    search's plan. With a ``planner`` and ``search`` set it also runs that search (the model's own plan, kept in
    ``planned``)."""

    config = None

    def __init__(self, planner: Planner | None = None):
        self.planner = planner  # the model's own search (None: score the fixed candidates only)
        self.candidates: torch.Tensor | None = None  # (N, H, A), set by the driver before each boundary
        self.costs: torch.Tensor | None = None  # (N,) after plan()
        self.search = False  # set by the driver: run the planner at this boundary
        self.own = False  # set by the driver: return the planner's result (this model drives the episode)
        self.execute: torch.Tensor | None = None  # (H, A) set by the driver: the chunk another model's plan runs
        self.planned: torch.Tensor | None = None  # (L, A) the planner's plan at this boundary (None: no search)

    def for_task(self, task) -> _Scorer:
        if self.planner is not None:
            self.planner = self.planner.for_task(task)  # the planner's task settings, as the planned policy's
        return self

    def plan(self, seed_actions: torch.Tensor, objective, *, generator=None, seed=None) -> PlanResult:
        cands = self.candidates[:, :seed_actions.shape[0]].to(seed_actions.device)  # (N, L, A)
        costs = objective(cands).detach().double().cpu()  # (N,)
        self.costs = costs
        self.planned = None
        if self.search and self.planner is not None:
            result = self.planner.plan(seed_actions, objective, generator=generator, seed=seed)
            self.planned = result.actions.detach().cpu()  # (L, A)
            if self.own:
                return result
        c0, cmin = float(costs[0]), float(costs.min())
        stats = IterationStats(0, float(costs.mean()), cmin, cmin, c0, 0.0)
        run = seed_actions if self.execute is None else self.execute[:seed_actions.shape[0]].to(seed_actions)
        return PlanResult(actions=run.clone(), mean=run.clone(), std=torch.zeros_like(run),
                          best_actions=cands[int(costs.argmin())], best_cost=cmin, history=[stats],
                          num_evaluations=len(cands))


@dataclass
class Scored:
    """One model: a label, its dynamics and the encoder its targets (and its simulator reference) use."""

    label: str
    dynamics: Dynamics
    encoder: Any
    policy: PlannedPolicyConfig | None = None  # e.g. gate_threshold: the model scored as that policy would
    cost: CostFn | None = None  # the model's own planning cost (its ranking and search); None: the run's cost


class FidelityPolicy(Policy):
    """Executes the WAM's chunks open loop; at each scored boundary builds the candidates and lets every
    model's PlannedPolicy and every simulator reference score them. ``records`` holds the costs."""

    name = "fidelity"

    def __init__(self, wam: WAM, models: Sequence[Scored], env, config: FidelityConfig,
                 cost: CostFn | None = None):
        self.wam, self.cfg, self.env = OnceWAM(wam), config, env
        self.chunk = wam.chunk_length
        self.arm = list(env.task.arm)  # the action entries whose summed shift is the arm's end-point shift
        self.task_metric = config.task_metric and TASK_METRIC in env.task.metrics
        cost = cost or make_cost("patch")
        self.labels = [m.label for m in models]
        if config.execute and config.execute not in self.labels:
            raise ValueError(f"execute={config.execute!r} names no scored model; choose one of {self.labels}")
        searching = {m.label for m in models if config.plan or m.label == config.execute}
        self.scorers = {m.label: _Scorer(make_planner(DEFAULT_PLANNER) if m.label in searching else None)
                        for m in models}
        self.policies = {m.label: PlannedPolicy(self.wam, self.scorers[m.label], m.dynamics, m.encoder,
                                                cost if m.cost is None else m.cost, config=m.policy) for m in models}
        self.reference: dict[str, str] = {}  # label -> simulator reference key (one per distinct encoder)
        self.sim_policies: dict[str, PlannedPolicy] = {}
        for m in models:
            key = repr(sorted(m.encoder.config_dict().items()))
            if key not in self.sim_policies:
                self.scorers["sim:" + key] = _Scorer()
                self.sim_policies[key] = PlannedPolicy(self.wam, self.scorers["sim:" + key],
                                                       SimulatorDynamics(env, m.encoder), m.encoder, cost)
            self.reference[m.label] = key
        self.records: list[dict[str, Any]] = []
        self.reset()

    def _all(self) -> list[PlannedPolicy]:
        return [*self.policies.values(), *self.sim_policies.values()]

    def reset(self, seed: int | None = None) -> None:
        self._seed = seed or 0
        self.wam.new_episode()
        for p in self._all():
            p.reset(seed)
        self._queue: list[np.ndarray] = []

    def wants_images(self, step: int) -> bool:
        return step % self.chunk == 0 or any(p.wants_images(step) for p in self._all())

    def _scored(self, step: int) -> bool:
        return step % self.chunk == 0 and step // self.chunk in self.cfg.boundaries

    def act(self, obs: Observation) -> np.ndarray:
        t = obs.step
        scored = self._scored(t)
        if t % self.chunk == 0:
            self._queue = self._boundary(obs, scored)
        else:
            for p in self._all():  # every policy sees every step (its history frames)
                p.act(obs)
        return self._queue.pop(0)

    def _boundary(self, obs: Observation, scored: bool) -> list[np.ndarray]:
        """Build the candidates, let every policy score them (the models first, the executing one before the
        others), record the scores at a scored boundary, and return the chunk to execute (H of (A,))."""
        t = obs.step
        out = self.wam.predict(obs, self.wam.default_instruction)
        chunk = np.clip(out.actions, -1, 1).astype(np.float32)  # (H, A)
        base = torch.from_numpy(chunk)  # (H, A)
        cands = base[None]  # (1, H, A): an unscored boundary only keeps every policy's history going
        if scored:
            g = torch.Generator().manual_seed(self.cfg.seed * 1_000_003 + self._seed * 1000 + t)
            noise = candidate_noise((self.cfg.num_candidates - 1, *base.shape), g, base.device)  # (N-1, H, A)
            cands = torch.cat([base[None], (base + self.cfg.sigma * noise).clamp(-1, 1)])  # (N, H, A)
        for label, s in self.scorers.items():
            s.candidates, s.costs, s.execute, s.planned = cands, None, None, None
            s.own = label == self.cfg.execute
            s.search = s.own or (scored and self.cfg.plan)
        executed = chunk
        if self.cfg.execute:  # its policy decides the chunk; every other policy's history records that chunk
            ex = self.policies[self.cfg.execute]
            ex.act(obs)
            executed = ex.last_decision.executed.astype(np.float32)  # (H, A)
            for label, s in self.scorers.items():
                s.execute = None if label == self.cfg.execute else torch.from_numpy(executed)
        for label, p in self.policies.items():
            if label != self.cfg.execute:
                p.act(obs)
                if self.cfg.execute and not np.allclose(p.last_decision.executed, executed, atol=1e-6):
                    raise ValueError(f"model {label!r} would record another chunk than {self.cfg.execute!r}'s plan "
                                     f"at step {t} (its rollout covers fewer steps, or its policy settings gate "
                                     f"its plan); score models of one frameskip with the default settings")
        plans = {label: torch.cat([self.scorers[label].planned, base[self.scorers[label].planned.shape[0]:]])
                 for label in self.labels if scored and self.scorers[label].planned is not None}  # label -> (H, A)
        if self.cfg.execute in plans:  # what ran, should the executor's settings have put the WAM's chunk instead
            plans[self.cfg.execute] = torch.from_numpy(executed)
        if plans:  # the simulator scores every model's plan after the fixed candidates, in the order of ``plans``
            extended = torch.cat([cands, torch.stack(list(plans.values()))])  # (N + M, H, A)
            for key in self.sim_policies:
                self.scorers["sim:" + key].candidates = extended
        for p in self.sim_policies.values():
            p.act(obs)
        if scored:
            self.records.append(self._score(t, cands, plans))
        return list(executed)

    def _score(self, t: int, cands: torch.Tensor, plans: dict[str, torch.Tensor]) -> dict[str, Any]:
        """One scored boundary's record: per model, its costs of the N candidates against the simulator's, and
        with ``plans`` (label -> (H, A)) each plan's true cost and gain over the WAM's chunk."""
        n = len(cands)
        slot = {label: n + i for i, label in enumerate(plans)}  # each plan's index after the N candidates
        rec = dict(seed=self._seed, step=t, models={})
        first = "sim:" + self.reference[self.labels[0]]
        for label in self.labels:
            model = self.scorers[label].costs
            true_all = self.scorers["sim:" + self.reference[label]].costs  # (N [+ M],)
            true = true_all[:n]
            covered = self.policies[label].dynamics.covered(self.chunk)  # the steps this model scores
            shift = (cands - cands[:1])[:, :covered].sum(dim=1)[:, self.arm]  # (N, arm entries): end-point shift
            rec["models"][label] = dict(boundary_stats(model, true, self.cfg.top_k, shift),
                                        model_costs=model.tolist(), true_costs=true.tolist())
            if label in slot:
                j, ref = slot[label], self.scorers[first].costs
                rec["models"][label].update(plan_stats(true_all[j], true[0], ref[j], ref[0]))
        if self.task_metric:
            rec["task"] = self._task(torch.cat([cands, *[p[None] for p in plans.values()]]))
            xy = rec["task"]["cand_xy_mm"]
            for label in self.labels:
                row = rec["models"][label]
                row.update(task_stats(torch.tensor(row["model_costs"]), torch.tensor(row["true_costs"]),
                                      torch.tensor(xy[:n])))
                if label in slot:
                    row["plan_xy_change_mm"] = float(xy[slot[label]] - xy[0])
        return rec

    def _task(self, cands: torch.Tensor) -> dict[str, Any]:
        """Step each candidate (N, H, A) from the boundary state, state only; the state is restored after."""
        env = self.env
        now = env.privileged_state()
        snap = env.snapshot()
        xy = []
        for cand in cands.numpy():  # (H, A)
            env.restore(snap)
            env.restore(snap)
            for a in cand:
                env.step(np.asarray(a, np.float32))
            s = env.privileged_state()
            xy.append(1000.0 * float(np.linalg.norm(s["cube_pose"][:2] - s["hole_pos"][:2])))
        env.restore(snap)
        env.restore(snap)
        return dict(boundary_xy_mm=1000.0 * float(np.linalg.norm(now["cube_pose"][:2] - now["hole_pos"][:2])),
                    grasped=bool(now["stages"][0]), lifted=bool(now["stages"][1]), cand_xy_mm=xy)

    def info(self) -> dict[str, Any]:
        return dict(boundaries=len([r for r in self.records if r["seed"] == self._seed]))


def run_fidelity(env, wam: WAM, models: Sequence[Scored], seeds: Sequence[int], config: FidelityConfig | None = None,
                 progress=None, cost: CostFn | None = None) -> dict[str, Any]:
    """Score every model at the ``boundaries`` of each seed's episode that it reaches. The episode runs the WAM's
    chunks open loop and stops after the last boundary's first step or at success; with ``config.execute`` it runs
    that model's plans to the episode's end (its closed loop), and ``episodes`` records each one's outcome.
    Returns {"records": [...], "summary": {...}, "episodes": [...]}."""
    from wamplan.policies.rollout import run_episode

    cfg = config or FidelityConfig()
    pol = FidelityPolicy(wam, models, env, cfg, cost=cost)
    episodes = []
    for seed in seeds:
        r = run_episode(env, pol, seed, max_steps=None if cfg.execute else max(cfg.boundaries) * pol.chunk + 1)
        episodes.append(dict(seed=seed, success=r.success, outcome=r.outcome, length=r.length))
        if progress is not None:
            progress(seed, r, pol.records)
    return dict(records=pol.records, summary=summarize(pol.records, pol.labels, cfg), episodes=episodes)


def _median(a: np.ndarray, p: float = 50) -> float:
    a = a[np.isfinite(a)]
    return float(np.percentile(a, p)) if len(a) else float("nan")


def _aggregate(records: Sequence[dict[str, Any]], label: str, cfg: FidelityConfig) -> dict[str, Any]:
    """Medians / IQR / means over the given boundaries of one model's per-boundary statistics."""
    rows = [r["models"][label] for r in records]
    col = {k: np.array([row[k] for row in rows], float) for k in
           ("spearman", "top_overlap", "pick_beats_wam", "random_beats_wam", "pick_gain", "best_gain", "true_spread",
            "slope_cosine")}
    mean = (lambda a: float(a.mean()) if len(a) else float("nan"))
    out = dict(boundaries=len(rows), spearman_median=_median(col["spearman"]),
               spearman_q25=_median(col["spearman"], 25), spearman_q75=_median(col["spearman"], 75),
               top_overlap_mean=mean(col["top_overlap"]), top_overlap_chance=cfg.top_k / cfg.num_candidates,
               pick_beats_wam=mean(col["pick_beats_wam"]), random_beats_wam=mean(col["random_beats_wam"]),
               pick_gain_median=_median(col["pick_gain"]), best_gain_median=_median(col["best_gain"]),
               true_spread_median=_median(col["true_spread"]), slope_cosine_median=_median(col["slope_cosine"]),
               slope_agree=mean((col["slope_cosine"][np.isfinite(col["slope_cosine"])] > 0).astype(float)))
    lifted = [row for r, row in zip(records, rows) if r.get("task", {}).get("lifted")]
    if lifted:
        out.update(lifted_boundaries=len(lifted), **{
            f"{k}_median": _median(np.array([row[k] for row in lifted], float)) for k in
            ("true_vs_xy", "model_vs_xy", "pick_xy_change_mm", "sim_pick_xy_change_mm", "best_xy_change_mm")})
    planned = [row for row in rows if "plan_gain" in row]
    if planned:
        out.update(plans=len(planned), plan_beats_wam=mean(np.array([row["plan_beats_wam"] for row in planned])),
                   **_mean_se("plan_gain", [row["plan_gain"] for row in planned]),
                   **_mean_se("plan_gain_ref", [row["plan_gain_ref"] for row in planned]))
        refs = [r["models"][next(iter(r["models"]))] for r in records]  # the first model's row, per boundary
        paired = [row["plan_gain_ref"] - ref["plan_gain_ref"] for row, ref in zip(rows, refs)
                  if row is not ref and "plan_gain_ref" in row and "plan_gain_ref" in ref]
        if paired:  # against the first model at the same boundaries: the paired difference and its error
            out.update(_mean_se("plan_gain_ref_vs_first", paired))
        moved = [row["plan_xy_change_mm"] for row in lifted if "plan_xy_change_mm" in row]
        if moved:
            out.update(_mean_se("plan_xy_change_mm", moved))
    return out


def _mean_se(key: str, values: Sequence[float]) -> dict[str, float]:
    """The mean of ``values`` (the finite ones), its standard error and median, as KEY_mean, KEY_se, KEY_median."""
    a = np.array(values, float)
    a = a[np.isfinite(a)]
    se = float(a.std(ddof=1) / np.sqrt(len(a))) if len(a) > 1 else float("nan")
    return {f"{key}_mean": float(a.mean()) if len(a) else float("nan"), f"{key}_se": se,
            f"{key}_median": _median(a)}


def summarize(records: Sequence[dict[str, Any]], labels: Sequence[str], cfg: FidelityConfig) -> dict[str, Any]:
    """Per model: the aggregate over all boundaries, and ``by_step``: the same per boundary step."""
    steps = sorted({r["step"] for r in records})
    return {label: dict(_aggregate(records, label, cfg),
                        by_step={s: _aggregate([r for r in records if r["step"] == s], label, cfg) for s in steps})
            for label in labels}


def format_fidelity(summary: dict[str, Any], top_k: int = 8) -> str:
    """One row per model."""
    head = (f"{'model':<16}{'bounds':>7}  {'Spearman med [IQR]':<22}{f'top-{top_k} ovl (chance)':>20}"
            f"{'pick>WAM (random)':>19}{'pick gain':>11}{'best gain':>11}{'true std/mean':>15}"
            f"{'slope cos (>0)':>16}")
    lines = [head]
    rows = [(label, s) for label, agg in summary.items()
            for s in [agg, *[dict(v, step=k) for k, v in agg.get("by_step", {}).items()]]]
    for label, s in rows:
        name = label if "step" not in s else f"  step {s['step']}"
        lines.append(f"{name:<16}{s['boundaries']:>7}  "
                     f"{s['spearman_median']:>5.2f} [{s['spearman_q25']:.2f}, {s['spearman_q75']:.2f}]".ljust(47)
                     + f"{s['top_overlap_mean']:>6.2f} ({s['top_overlap_chance']:.2f})".rjust(20)
                     + f"{s['pick_beats_wam']:>6.0%} ({s['random_beats_wam']:.0%})".rjust(19)
                     + f"{s['pick_gain_median']:>10.1%} {s['best_gain_median']:>10.1%}"
                     + f"{s['true_spread_median']:>15.1%}"
                     + f"{s['slope_cosine_median']:>8.2f} ({s['slope_agree']:.0%})".rjust(16))
    lines.append("gains: the true (simulator) cost's relative drop from the WAM's chunk to the model's pick / to the "
                 "simulator's best candidate; medians over boundaries. slope cos: cosine of the model's and the "
                 "simulator's cost slopes over the candidates' end-point shifts (median; share of boundaries > 0)")
    for label, s in rows:
        if s.get("lifted_boundaries"):
            label = label if "step" not in s else f"{label} step {s['step']}"
            lines.append(f"{label}: {s['lifted_boundaries']} lifted; Spearman vs cube-hole xy after the chunk: "
                         f"true cost {s['true_vs_xy_median']:.2f}, model {s['model_vs_xy_median']:.2f}; "
                         f"xy change vs the WAM's chunk (mm, median): model's pick "
                         f"{s['pick_xy_change_mm_median']:+.1f}, simulator's pick "
                         f"{s['sim_pick_xy_change_mm_median']:+.1f}, "
                         f"best candidate {s['best_xy_change_mm_median']:+.1f}")
    for label, s in rows:
        if s.get("plans"):
            label = label if "step" not in s else f"{label} step {s['step']}"
            xy = (f"; the cube's xy change vs the WAM's chunk {s['plan_xy_change_mm_mean']:+.2f} "
                  f"± {s['plan_xy_change_mm_se']:.2f} mm (lifted)" if "plan_xy_change_mm_mean" in s else "")
            lines.append(f"{label}: its own search's plan, {s['plans']} boundaries: beats the WAM's chunk in the "
                         f"simulator {s['plan_beats_wam']:.0%}; true-cost gain {s['plan_gain_mean']:+.2%} "
                         f"± {s['plan_gain_se']:.2%} (median {s['plan_gain_median']:+.2%}), in the first model's "
                         f"cost {s['plan_gain_ref_mean']:+.2%} ± {s['plan_gain_ref_se']:.2%}{xy}"
                         + (f"; minus the first model's at the same boundaries {s['plan_gain_ref_vs_first_mean']:+.2%}"
                            f" ± {s['plan_gain_ref_vs_first_se']:.2%}" if "plan_gain_ref_vs_first_mean" in s else ""))
    return "\n".join(lines)
