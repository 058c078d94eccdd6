"""Run evaluation conditions over seeds: one worker per process, records appended as episodes finish.

Every condition runs the same seeds. A job is one (condition, seed); a worker builds the env, the WAM
and the world models once and a policy per condition on first use. Re-running the same command skips
the jobs already recorded, so an interrupted evaluation resumes without repeating or losing episodes.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from wamplan.config import field, require, to_dict
from wamplan.evaluation.conditions import CONDITIONS
from wamplan.evaluation.records import append_record, read_records, record_key
from wamplan.parallel import imap_workers


@dataclass(frozen=True)
class EvalConfig:
    wam: str = field("", "WAM checkpoint directory (e.g. a TinyWAM)")
    wm_plain: str = field("", "plain world model checkpoint (condition 6)")
    wm_augmented: str = field("", "augmented world model checkpoint (condition 7)")
    planner: str = field("cem", "cem or mppi")
    num_candidates: int = field(32, "candidates per iteration (the mean + samples)")
    num_elites: int = field(8, "CEM elites")
    iterations: int = field(4, "optimiser iterations per chunk")
    init_std: float = field(0.10, "initial sampling std (normalised action units)")
    first_chunk: str = field("open-loop", "open-loop (paper) or rest-history")
    sim_encoder: str = field("", "encoder for the simulator conditions (default: the plain world model's)")
    camera_size: int = field(224, "rendered image size")
    max_steps: int = field(300, "episode step limit")
    device: str = field("auto", "torch device for the models")

    def __post_init__(self):
        require(self.first_chunk in ("open-loop", "rest-history"),
                f"first_chunk must be open-loop or rest-history, got {self.first_chunk!r}")
        require(self.planner in ("cem", "mppi"), f"planner must be cem or mppi, got {self.planner!r}")

    def check_for(self, conditions: list[int]) -> None:
        from wamplan.errors import UserError

        if not self.wam:
            raise UserError("--wam CKPT is required (a WAM checkpoint, e.g. from `wamplan wam train`)")
        for c in conditions:
            need = {"learned-plain": ("wm_plain", "--wm-plain"), "learned-augmented": ("wm_augmented", "--wm-augmented")}
            if CONDITIONS[c].dynamics in need:
                attr, flag = need[CONDITIONS[c].dynamics]
                if not getattr(self, attr):
                    raise UserError(f"condition {c} needs {flag} CKPT (a world model from `wamplan wm train`)")
                if not Path(getattr(self, attr)).exists():
                    raise UserError(f"{flag} {getattr(self, attr)} does not exist; train it or fix the path")
        if not Path(self.wam).exists():
            raise UserError(f"--wam {self.wam} does not exist; train one with `wamplan wam train` or fix the path")


class EvalWorker:
    """Holds the env, the WAM, the models; ``worker((condition, seed))`` runs one episode -> record."""

    def __init__(self, cfg: EvalConfig):
        from wamplan.envs.core import EnvConfig, InsertionEnv
        from wamplan.wam import load_wam

        self.cfg = cfg
        self.env = InsertionEnv(EnvConfig(camera_size=cfg.camera_size, max_episode_steps=cfg.max_steps))
        self.wam = load_wam(cfg.wam, device=cfg.device)
        self._models: dict[str, Any] = {}
        self._policies: dict[int, Any] = {}

    def _world_model(self, path: str):
        from wamplan.worldmodel.train import load_world_model

        if path not in self._models:
            self._models[path] = load_world_model(path, device=self.cfg.device)
        return self._models[path]  # (predictor, encoder)

    def _sim_encoder(self):
        from wamplan.device import resolve_device
        from wamplan.encoders import make_encoder

        if self.cfg.sim_encoder:
            return make_encoder(self.cfg.sim_encoder).to(resolve_device(self.cfg.device))
        if self.cfg.wm_plain or self.cfg.wm_augmented:
            return self._world_model(self.cfg.wm_plain or self.cfg.wm_augmented)[1]
        return make_encoder("patch-pixels").to(resolve_device(self.cfg.device))

    def policy(self, cid: int):
        if cid in self._policies:
            return self._policies[cid]
        from wamplan.planning import CEMConfig, MPPIConfig, make_cost, make_planner
        from wamplan.planning.dynamics import LearnedDynamics, SimulatorDynamics
        from wamplan.planning.policy import PlannedPolicy, PlannedPolicyConfig
        from wamplan.wam import WAMPolicy
        from wamplan.wam.oracle import ExpertOracleWAM

        c, cfg = CONDITIONS[cid], self.cfg
        if c.dynamics == "none":
            pol = WAMPolicy(self.wam)
        else:
            if c.dynamics == "simulator":
                enc = self._sim_encoder()
                dyn = SimulatorDynamics(self.env, enc)
            else:
                model, enc = self._world_model(cfg.wm_plain if c.dynamics == "learned-plain" else cfg.wm_augmented)
                dyn = LearnedDynamics(model)
            common = dict(num_candidates=cfg.num_candidates, iterations=cfg.iterations, init_std=cfg.init_std)
            pcfg = (CEMConfig(num_elites=cfg.num_elites, **common) if cfg.planner == "cem" else MPPIConfig(**common))
            oracle = ExpertOracleWAM(self.env) if "expert" in (c.seed, c.target) else None
            seed_wam = oracle if c.seed == "expert" else self.wam
            target_wam = oracle if c.target == "expert" else self.wam
            pol = PlannedPolicy(seed_wam, make_planner(cfg.planner, pcfg), dyn, enc, make_cost("patch"),
                                target_wam=target_wam, config=PlannedPolicyConfig(first_chunk=cfg.first_chunk))
        self._policies[cid] = pol
        return pol

    def __call__(self, job: tuple[int, int]) -> dict[str, Any]:
        from wamplan.envs.rollout import run_episode

        cid, seed = job
        r = run_episode(self.env, self.policy(cid), seed, max_steps=self.cfg.max_steps)
        chunks = r.policy_info.get("chunks")  # PlannedPolicy: per-chunk records; WAMPolicy: a count
        planned = [ch for ch in chunks if ch.get("planned")] if isinstance(chunks, list) else []
        timing = {k: float(np.mean([ch[k] for ch in planned])) for k in ("wam_s", "target_encode_s", "search_s")} \
            if planned else {}
        wam_s = r.policy_info.get("wam_query_s")
        if wam_s is not None and not timing:
            timing = {"wam_s": float(np.mean(wam_s)) if isinstance(wam_s, list) else float(wam_s)}
        return dict(condition=cid, seed=seed, variant=self.cfg.first_chunk, success=r.success, outcome=r.outcome,
                    length=r.length, reached=r.reached, wall_time_s=round(r.wall_time, 2),
                    planned_chunks=len(planned), open_loop_chunks=r.policy_info.get("open_loop_chunks", {}),
                    chunk_timing_s=timing,
                    chunks=[{k: (round(v, 4) if isinstance(v, float) else v) for k, v in ch.items()} for ch in planned],
                    finished=time.time())


def _same(a: Any, b: Any) -> bool:
    """Equal settings; two spellings of one checkpoint path (relative, absolute, through a link) count as one."""
    if a == b:
        return True
    return isinstance(a, str) and isinstance(b, str) and bool(a and b) and Path(a).exists() and \
        os.path.realpath(a) == os.path.realpath(b)


def _check_same_settings(out: Path, cfg: EvalConfig) -> None:
    """Records of one directory must come from one configuration. The first-chunk variant may differ
    (Table 2), the device does not matter, and a world model not given before may be added later."""
    from wamplan.errors import UserError

    path = out / "eval_config.json"
    now = {k: v for k, v in to_dict(cfg).items() if k not in ("first_chunk", "device")}
    if path.is_file():
        before = json.loads(path.read_text())
        addable = ("wm_plain", "wm_augmented", "sim_encoder")
        diff = {k: (before.get(k), now.get(k)) for k in set(before) | set(now)
                if not _same(before.get(k), now.get(k)) and not (k in addable and not (before.get(k) and now.get(k)))}
        if diff:
            raise UserError(f"{out} holds an evaluation with other settings {diff} (stored, requested); "
                            f"use another --out or the same settings")
        now = {k: before.get(k) or now.get(k) for k in set(before) | set(now)}
    path.write_text(json.dumps(now, indent=1, sort_keys=True) + "\n")


def run_evaluation(cfg: EvalConfig, conditions: list[int], seeds: list[int], out_dir: str | Path,
                   workers: int = 1) -> Iterator[dict[str, Any]]:
    """Run the missing (condition, seed) jobs, appending each record as it finishes; yields the records."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    done = {record_key(r) for r in read_records(out, repair=True)}
    # Seed-major order: a run stopped early (or fanned out and cut short) has every condition on the same
    # seeds, so its partial table still compares like with like.
    jobs = [(c, s) for s in seeds for c in conditions if (c, s, cfg.first_chunk) not in done]
    _check_same_settings(out, cfg)
    for rec in imap_workers(partial(EvalWorker, cfg), jobs, workers):
        append_record(out, rec)
        yield rec
