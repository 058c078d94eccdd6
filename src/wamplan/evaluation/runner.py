"""Run evaluation conditions over seeds: one worker per process (or Ray actor), records appended by this
process as episodes finish.

Every condition runs the same seeds. A job is one (condition, seed); a worker builds the env, the WAM
and the world models once and a policy per condition on first use. Re-running the same command skips
the jobs already recorded, so an interrupted evaluation resumes without repeating or losing episodes.
Every record of a task that measures the cube (``CubeTrace.fits``) also carries the cube's privileged path
(``trace``, every ``TRACE_EVERY`` steps), where it was finally let go (``release``, found at every step) and
whether it was still held at the end, for reading failures; no policy sees them.

The task is the env's (``--task``): a WAM or world model made for another task stops the run in one line, before
its settings are stored.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import time
from contextlib import ExitStack
from functools import partial
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from wamplan.config import ENSEMBLES_LAST, joined_checkpoints, one_checkpoint, to_dict
from wamplan.envs.spec import check_same_task
from wamplan.evaluation.conditions import CONDITIONS
from wamplan.evaluation.config import EvalConfig
from wamplan.evaluation.records import CONFIG, RECORDS, append_record, read_records, read_settings, record_key
from wamplan.evaluation.videos import VideoConfig, write_record_videos
from wamplan.locks import dir_lock
from wamplan.parallel import Backend, imap_workers
from wamplan.planning.dynamics import task_name
from wamplan.planning.gates import DISCARDED
from wamplan.planning.defaults import DEFAULT_PLANNER

TRACE_EVERY = 4  # steps between the cube's privileged samples in a record's "trace" (evaluation/trace.py)
VIDEO_KEY, VIDEO_ERROR_KEY = "_videos", "_video_error"  # a filmed episode's videos / failure, never stored


class EvalWorker:
    """Holds the env, the WAM, the models; ``worker((condition, seed))`` runs one episode -> record. With ``videos``
    the episodes of the ``filmed`` seeds are filmed (:mod:`wamplan.evaluation.filming`): their record carries the
    encoded videos under :data:`VIDEO_KEY` (and why filming failed under :data:`VIDEO_ERROR_KEY`), which the driver
    writes out and removes before it stores the record."""

    def __init__(self, cfg: EvalConfig, videos: VideoConfig | None = None, filmed: frozenset[int] = frozenset()):
        from wamplan.envs.core import TaskEnv
        from wamplan.wam import load_wam

        self.cfg = cfg
        self.videos, self.filmed = videos, frozenset(filmed)
        self._decoders: dict[int, Any] = {}  # id(encoder) -> the plan videos' picture decoder for its tokens
        self.env = TaskEnv(cfg.env)
        if cfg.wam_url:
            from wamplan.wam.cosmos_client import CosmosPolicyClient

            self.wam = CosmosPolicyClient(profile=cfg.wam_profile, url=cfg.wam_url, task=cfg.env.task,
                                          send_chunk_frames=cfg.wam_send_chunk_frames)
        else:
            self.wam = load_wam(cfg.wam, device=cfg.device)
        check_wam_task(cfg, self.wam)
        self._models: dict[str, Any] = {}
        self._policies: dict[int, Any] = {}

    def _world_model(self, path: str):
        from wamplan.worldmodel.load import load_world_model

        if path not in self._models:
            self._models[path] = load_world_model(path, device=self.cfg.device, dtype=self.cfg.wm_dtype)
            check_world_model_task(self.cfg, path, self._models[path][0])
        return self._models[path]  # (predictor, encoder)

    def _sim_encoder(self):
        return sim_encoder(self.cfg, lambda path: self._world_model(path)[1])

    def policy(self, cid: int):
        if cid in self._policies:
            return self._policies[cid]
        from wamplan.planning.build import planned_policy
        from wamplan.planning.dynamics import BlendedDynamics, LearnedDynamics, SimulatorDynamics
        from wamplan.wam import WAMPolicy
        from wamplan.wam.oracle import ExpertOracleWAM

        c, cfg = CONDITIONS[cid], self.cfg
        if c.dynamics == "none":
            pol = WAMPolicy(self.wam)
        else:
            if c.dynamics == "simulator":
                enc = self._sim_encoder()
                dyn, paths = SimulatorDynamics(self.env, enc), []
            else:
                paths = [cfg.world_model(cid)]
                predictor, enc = self._world_model(paths[0])
                dyn = LearnedDynamics(predictor)
                if cfg.oracle_blend > 0:  # the simulator encodes with the model's encoder: one embedding space
                    dyn = BlendedDynamics(dyn, SimulatorDynamics(self.env, enc), cfg.oracle_blend)
            oracle = ExpertOracleWAM(self.env) if "expert" in (c.seed, c.target) else None
            seed_wam = oracle if c.seed == "expert" else self.wam
            target_wam = oracle if c.target == "expert" else self.wam
            pol = planned_policy(seed_wam, dyn, enc, cfg.planning, target_wam=target_wam, world_models=paths)
        self._policies[cid] = pol
        return pol

    def __call__(self, job: tuple[int, int]) -> dict[str, Any]:
        from wamplan.evaluation.trace import CubeTrace
        from wamplan.policies.rollout import run_episode

        cid, seed = job
        trace = CubeTrace(every=TRACE_EVERY) if CubeTrace.fits(self.env.task) else None
        film = self._film(cid, seed)
        hooks = [h for h in (trace, film) if h is not None]
        r = run_episode(self.env, self.policy(cid), seed, max_steps=self.cfg.env.episode_steps,
                        images_at=film.images_at if film else None,
                        on_obs=(lambda env, obs, a: [h(env, obs, a) for h in hooks]) if hooks else None)
        videos = film.finish(self.env, r.length) if film else None  # {"episode": WebM bytes, "plan": ...}
        chunks = r.policy_info.get("chunks")  # PlannedPolicy: per-chunk records; WAMPolicy: a count
        planned = [ch for ch in chunks if ch.get("planned")] if isinstance(chunks, list) else []
        searched = [ch for ch in chunks if ch.get("planned") or ch.get("open_loop") in DISCARDED] \
            if isinstance(chunks, list) else []  # a discarded plan was searched too: its time and costs count
        timing = {k: float(np.mean([ch[k] for ch in searched])) for k in ("wam_s", "target_encode_s", "search_s")} \
            if searched else {}
        wam_s = r.policy_info.get("wam_query_s")
        if wam_s is not None and not timing:
            timing = {"wam_s": float(np.mean(wam_s)) if isinstance(wam_s, list) else float(wam_s)}
        return dict(condition=cid, seed=seed, variant=self.cfg.policy.first_chunk, success=r.success, outcome=r.outcome,
                    length=r.length, reached=r.reached, wall_time_s=round(r.wall_time, 2),
                    planned_chunks=len(planned), open_loop_chunks=r.policy_info.get("open_loop_chunks", {}),
                    chunk_timing_s=timing,
                    chunks=[{k: (round(v, 4) if isinstance(v, float) else v) for k, v in ch.items()} for ch in searched],
                    **({"proxy": r.policy_info["proxy"]} if "proxy" in r.policy_info else {}),
                    **(trace.summary() if trace else {}), **self._blend(cid), finished=time.time(),
                    **({VIDEO_KEY: videos} if videos else {}),
                    **({VIDEO_ERROR_KEY: film.error} if film and film.error else {}))

    def _film(self, cid: int, seed: int):
        """The :class:`~wamplan.evaluation.filming.EpisodeFilm` of episode (``cid``, ``seed``), or None if unfilmed."""
        if self.videos is None or seed not in self.filmed:
            return None
        from wamplan.evaluation.filming import EpisodeFilm, load_plan_decoder

        policy, plan = self.policy(cid), CONDITIONS[cid].dynamics != "none"
        decoder = load_plan_decoder(self.videos.decoder, policy, self.cfg.env.spec.name, self._decoders) \
            if plan else None
        return EpisodeFilm(policy, self.env.task.cameras, self.videos, plan=plan, decoder=decoder)

    def _blend(self, cid: int) -> dict[str, float]:
        """The record's mark of the --oracle-blend diagnostic, where it changed the dynamics (none otherwise)."""
        return {"oracle_blend": self.cfg.oracle_blend} if CONDITIONS[cid].learned and self.cfg.oracle_blend > 0 else {}


def check_wam_task(cfg: EvalConfig, wam: Any) -> None:
    """One line when ``wam`` was made for another task than the evaluation's (``--task``)."""
    check_same_task(cfg.env.task, task_name(wam), f"WAM {cfg.wam or cfg.wam_url}")


def check_world_model_task(cfg: EvalConfig, path: str, predictor: Any) -> None:
    """One line when the world model loaded from ``path`` was made for another task than the evaluation's."""
    check_same_task(cfg.env.task, task_name(predictor), f"world-model checkpoint {path}")


def _same(a: Any, b: Any) -> bool:
    """Equal settings; two spellings of one checkpoint path (relative, absolute, through a link) count as one."""
    if a == b:
        return True
    return isinstance(a, str) and isinstance(b, str) and bool(a and b) and Path(a).exists() and \
        os.path.realpath(a) == os.path.realpath(b)


def settings(cfg: EvalConfig) -> dict[str, Any]:
    """The settings records of one directory must share, flat (``"planner_config.temperature": 0.1``), as they
    ran: the planner's task settings filled from the task, the episode length resolved (the task's when not
    given). The first-chunk variant may differ (Table 2) and the device does not matter. The served-WAM keys and
    ``--requery-every`` appear only when set, so directories written before they existed keep their settings."""
    ran = dataclasses.replace(cfg, planner_config=cfg.task_planner_config,
                              env=dataclasses.replace(cfg.env, max_episode_steps=cfg.env.episode_steps))
    return {k: v for k, v in _flat(to_dict(ran)).items() if k not in ("policy.first_chunk", "device")
            and not (k in ("wam_url", "wam_profile", "policy.requery_every") and not v)}


def config_from_settings(out: str | Path, variant: str = "open-loop", device: str = "auto") -> EvalConfig:
    """The :class:`EvalConfig` the evaluation in ``out`` ran with, rebuilt from its stored settings
    (``eval_config.json``, :func:`settings`), for the records of first-chunk ``variant`` (not stored: one directory may
    hold several), on ``device``; one line if ``out`` stores none or settings this version cannot build."""
    from wamplan.config import ConfigError, from_dict
    from wamplan.errors import UserError
    from wamplan.evaluation.records import no_records

    stored = read_settings(out)
    if stored is None:
        raise UserError(no_records(out))
    nested: dict[str, Any] = {}
    for key, value in _without_retired(Path(out), stored).items():
        *parents, name = key.split(".")
        d = nested
        for part in parents:
            d = d.setdefault(part, {})
        d[name] = value
    nested.setdefault("policy", {})["first_chunk"] = variant
    try:
        return from_dict(EvalConfig, dict(nested, device=device))
    except ConfigError as e:
        raise UserError(f"{Path(out) / CONFIG} holds settings this wamplan cannot run ({e}); re-run the episode with "
                        f"the wamplan version that made it") from None


def _flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {prefix + k: v})
    return out


def _check_same_settings(out: Path, cfg: EvalConfig) -> None:
    """Check ``cfg`` against the settings ``out`` holds (:func:`_settings_to_store`), then store them."""
    _store_settings(out, _settings_to_store(out, cfg))


def _store_settings(out: Path, now: dict[str, Any]) -> None:
    (out / CONFIG).write_text(json.dumps(now, indent=1, sort_keys=True) + "\n")


# Settings that left the core (no measured gain; their record is in the lab's table) at the value that ran what runs
# now: a directory that stored one of them at that value resumes, another value is refused.
RETIRED = {"planner_config.noise_beta": 0.0, "policy.gate_above": None, "policy.rank_gate": None,
           "policy.replan_every": None, "policy.bias_correction": 0.0, "policy.correction_gain": 1.0,
           "cost.foreground": "", "cost.background_weight": 0.1, "cost.state_weight": 0.0,
           "policy.disagreement_weight": 0.0}


def _without_retired(out: Path, before: dict[str, Any]) -> dict[str, Any]:
    """The stored settings ``before`` without the :data:`RETIRED` ones; one line if one ran at another value, or if
    a condition planned in an ensemble of world models (several checkpoints joined by + or commas)."""
    from wamplan.errors import UserError

    for k in ("wm_plain", "wm_augmented"):
        if isinstance(before.get(k), str) and joined_checkpoints(before[k]):
            raise UserError(f"{out} holds an evaluation run with --{k.replace('_', '-')} {before[k]}, an ensemble of "
                            f"world models, which wamplan no longer plans in (it measured no gain); use another --out "
                            f"(or resume it at commit {ENSEMBLES_LAST})")
    for k, v in RETIRED.items():
        if k in before and before[k] != v:
            section, name = k.split(".", 1)
            flag = "--" + ("cost-" if section == "cost" else "") + name.replace("_", "-")
            raise UserError(f"{out} holds an evaluation run with {flag} {before[k]}, an option wamplan no longer has "
                            f"(it measured no gain); use another --out")
    return {k: v for k, v in before.items() if k not in RETIRED}


def _settings_to_store(out: Path, cfg: EvalConfig, recorded: bool = True) -> dict[str, Any]:
    """Records of one directory must come from one configuration (see :func:`settings`); a world model
    or simulator encoder not given before may be added later. ``recorded``: ``out`` holds records; settings
    stored without any (a run that failed before its first episode ended) bind nothing and are replaced.
    Returns the settings to store (nothing is written)."""
    from wamplan.errors import UserError

    now = settings(cfg)
    stored = read_settings(out) if recorded else None  # one line if damaged
    if stored is not None:
        before = _without_retired(out, stored)
        ran = before.get("planner", "cem")  # a directory that names no planner was written when cem was the default
        if ran != now["planner"]:
            raise UserError(f"{out} holds an evaluation with --planner {ran} (eval's default is {DEFAULT_PLANNER} "
                            f"now, cem in older versions); add --planner {ran} to resume it, or use another --out")
        addable = ("wm_plain", "wm_augmented", "sim_encoder")
        # a setting newer than the directory, requested at its default, is what the older version ran with
        default = settings(EvalConfig(planner=cfg.planner))
        diff = {k: (before.get(k), now.get(k)) for k in set(before) | set(now)
                if not _same(before.get(k), now.get(k)) and not (k in addable and not (before.get(k) and now.get(k)))
                and not (k not in before and k in default and _same(now[k], default[k]))}
        if diff:
            raise UserError(f"{out} holds an evaluation with other settings {diff} (stored, requested); "
                            f"use another --out or the same settings")
        now = {k: before.get(k) or now.get(k) for k in set(before) | set(now)}
    return now


def sim_encoder(cfg: EvalConfig, model_encoder: Callable[[str], Any]):
    """The encoder the simulator conditions (2-5) encode with: ``--sim-encoder``, else the plain world model's, else
    the augmented one's (``model_encoder(path)``: one embedding space with conditions 6 and 7), else patch-pixels."""
    from wamplan.device import resolve_device
    from wamplan.encoders import make_encoder

    if cfg.sim_encoder:
        return make_encoder(cfg.sim_encoder).to(resolve_device(cfg.device))
    if cfg.wm_plain or cfg.wm_augmented:
        flag = "--wm-plain" if cfg.wm_plain else "--wm-augmented"
        return model_encoder(one_checkpoint(cfg.wm_plain or cfg.wm_augmented, flag))
    return make_encoder("patch-pixels").to(resolve_device(cfg.device))


def _check_inputs(cfg: EvalConfig, conditions: list[int], videos: VideoConfig | None = None) -> None:
    """Load the WAM and the world models the conditions need once, here, on the CPU (and the plan videos'
    ``--decoder`` with each world model's encoder): a damaged or foreign checkpoint stops the run (in one line)
    before it stores its settings, so a failed start never locks its output directory. The workers load their own
    copies."""
    from wamplan.errors import UserError, require_paths
    from wamplan.planning.costs import pool_fits
    from wamplan.planning.policy_config import check_frameskip
    from wamplan.worldmodel.load import load_world_model

    if cfg.wam:
        from wamplan.wam import load_wam

        wam = load_wam(cfg.wam, device="cpu")
        try:
            check_wam_task(cfg, wam)
        finally:
            wam.close()
    spec = cfg.env.spec
    load = functools.cache(lambda path: load_world_model(path, device="cpu"))  # (predictor, encoder), each once
    for c in sorted(set(conditions)):
        path = cfg.world_model(c)
        if path:
            predictor, encoder = load(path)
            check_world_model_task(cfg, path, predictor)
            check_frameskip(predictor.cfg.frameskip, cfg.env.spec.chunk_len)
            n, k = predictor.cfg.num_patches, cfg.cost.pool
            if k > 1 and not pool_fits(n, k):
                raise UserError(f"--cost-pool {k} needs a square token grid whose side {k} divides, but {path} "
                                f"predicts {n} tokens a view; pass a divisor of {math.isqrt(n)}")
            if videos is not None and videos.first != 0 and videos.decoder:  # another kind, task or encoder: one line
                from wamplan.worldmodel.decoder import load_decoder

                require_paths([videos.decoder], "--decoder", "train one with `wamplan wm train-decoder`")
                load_decoder(videos.decoder, encoder=encoder, task=spec.name)


def run_evaluation(cfg: EvalConfig, conditions: list[int], seeds: list[int], out_dir: str | Path,
                   workers: int = 1, backend: Backend = Backend(), videos: VideoConfig | None = None
                   ) -> Iterator[dict[str, Any]]:
    """Run the missing (condition, seed) jobs on ``backend``, appending each record as it finishes (here, in the
    driver, whatever runs the episodes); yields the records. The checks (settings, inputs, the video directory and
    codec) run when this is called, before the first record is asked for. The directory is held (``.lock``,
    :func:`wamplan.locks.dir_lock`) from then until the last record is written: a second evaluation into it is
    refused in one line. ``videos`` (None: none) films the episodes of its chosen seeds into ``out/videos``
    (:mod:`wamplan.evaluation.videos`), each episode's videos written before its record."""
    from wamplan.errors import require_dir, require_own_dir

    backend.check()
    out = require_dir(out_dir)
    require_own_dir(out, (RECORDS, CONFIG), "an evaluation directory")  # not a store or a training run
    if videos is not None and videos.first != 0:  # a directory or codec that cannot take them: before any episode
        from wamplan.envs.media import require_webm
        from wamplan.evaluation.videos import require_video_dir

        require_webm()
        require_video_dir(out)
    held, locked = ExitStack(), out.is_dir()
    try:
        if locked:  # held from here: a second evaluation into it is refused before it loads anything
            held.enter_context(dir_lock(out, "evaluated into"))
        now, jobs = _todo(out, cfg, conditions, seeds)
        if jobs:
            _check_inputs(cfg, conditions, videos)
        if not locked:  # a new directory, made only now that the inputs loaded: a failed start leaves none
            out.mkdir(parents=True, exist_ok=True)
            held.enter_context(dir_lock(out, "evaluated into"))
            now, jobs = _todo(out, cfg, conditions, seeds)  # what another run recorded there meanwhile counts
        _store_settings(out, now)  # and a directory that held a run stays free for it
    except BaseException:
        held.close()
        raise
    filmed = videos.filmed(seeds) if videos is not None else frozenset()
    return _run_jobs(partial(EvalWorker, cfg, videos, filmed), jobs, out, workers, backend, held)


def _todo(out: Path, cfg: EvalConfig, conditions: list[int], seeds: list[int]
          ) -> tuple[dict[str, Any], list[tuple[int, int]]]:
    """(the settings to store, the (condition, seed) jobs ``out`` has not recorded); read under ``out``'s lock, so a
    torn last record (a kill mid-write) is cut off."""
    done = {record_key(r) for r in read_records(out, repair=True)}
    # Seed-major order: a run stopped early (or fanned out and cut short) has every condition on the same
    # seeds, so its partial table still compares like with like.
    jobs = [(c, s) for s in seeds for c in conditions if (c, s, cfg.policy.first_chunk) not in done]
    return _settings_to_store(out, cfg, recorded=bool(done)), jobs


def _run_jobs(make_worker: Callable[[], EvalWorker], jobs: list[tuple[int, int]], out: Path, workers: int,
              backend: Backend, held: ExitStack) -> Iterator[dict[str, Any]]:
    with held:  # the directory's lock, released with the last record (or when the caller stops asking)
        for rec in imap_workers(make_worker, jobs, workers, backend):
            write_record_videos(out, rec, rec.pop(VIDEO_KEY, None), rec.pop(VIDEO_ERROR_KEY, None))
            append_record(out, rec)
            yield rec
