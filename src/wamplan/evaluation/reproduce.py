"""``wamplan reproduce``: the paper's whole pipeline, stage by stage, as library calls.

collect expert / noisy / pink -> train TinyWAM -> collect on-policy rollouts of it -> train the plain and
the augmented world models (and the picture decoder) -> evaluate the conditions -> report. The sizes
come from ``wamplan.presets``. A finished stage is recorded with its duration in ``OUT/stage_times.json``
and skipped when the command is run again; a stage cut short resumes inside itself (the stores,
trainers and evaluation records are resumable). Each stage prints the ``wamplan`` command line that
does the same, to re-run or inspect one stage by hand.

Every stage runs in one task (``task``, ``--task``; default cube-insertion): its env collects and evaluates, and
the models learn from its stores. The pipeline starts from demonstrations: the task's scripted expert
(``TaskSpec.expert``) and its noisy variant, or, for a task without one whose ``TaskSpec.demonstrations`` is
ManiSkill's motion planner, that planner's solutions (``scripts/maniskill_demos.sh``, on seeds from 10000, twice
the demonstrations needed), imported (``wamplan data import``) as the ``expert`` store (source ``demo``) and replayed
with noise (σ 0.1 on the arm) as the ``noisy`` store. One line for a task with neither.
"""

from __future__ import annotations

import json
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from wamplan.envs.config import EnvConfig
from wamplan.envs.spec import get_task
from wamplan.errors import UserError
from wamplan.presets import PRESETS, Preset, get_preset

__all__ = ["PRESETS", "SEED_BASE", "Call", "Stage", "plan", "stages", "reproduce"]

PAPER_PLANNER = "cem"  # the paper's experiment uses the paper's CEM (wamplan eval defaults to --planner wamplan)
SEED_BASE = {"expert": 1000, "noisy": 2000, "pink": 3000, "on_policy": 4000,  # evaluation uses seeds 0..49
             "demos": 10000}
DEMO_NOISE = 0.1  # std of the noise on the arm's entries of the noisy replays of demonstrations
DEMOS_SCRIPT = Path(__file__).resolve().parents[3] / "scripts" / "maniskill_demos.sh"  # in a source checkout
TIMES_FILE = "stage_times.json"


@dataclass(frozen=True)
class Call:
    """One library call of a stage, with the ``wamplan`` command line that does the same."""

    fn: Callable[..., Any]
    kwargs: dict[str, Any] = field(default_factory=dict)
    command: tuple[str, ...] = ()

    def __call__(self) -> Any:
        return self.fn(**self.kwargs)

    def line(self) -> str:
        """The shell line (a ``wamplan`` command, or a script of the checkout)."""
        return " ".join(self.command if self.command[0].startswith("scripts/") else ("wamplan", *self.command))


@dataclass(frozen=True)
class Stage:
    name: str
    calls: tuple[Call, ...]


def _camera_flag(env: EnvConfig) -> list[str]:
    """``--camera-size N`` for the printed command lines where it is not the default."""
    return [] if env.camera_size == EnvConfig.camera_size else ["--camera-size", str(env.camera_size)]


def _env_flags(env: EnvConfig) -> list[str]:
    """``--task`` and ``--camera-size`` for the printed command lines, where they differ from the defaults."""
    return ([] if env.task == EnvConfig.task else ["--task", env.task]) + _camera_flag(env)


def _collect(source: str, p: Preset, store: Path, workers: int, seeds: int, policy: str | None = None,
             max_steps: int | None = None, *, env: EnvConfig) -> Call:
    from wamplan.data.collect import collect
    from wamplan.evaluation.build import load_policy

    key = "on_policy" if source == "policy" else source.removesuffix("-expert")
    cmd = ["collect", "--source", source, *(["--policy", policy] if policy else []), "--episodes", str(seeds),
           "--seed-start", str(SEED_BASE[key]), *(["--max-steps", str(max_steps)] if max_steps else []),
           "--out", str(store), "--image-every", str(p.image_every), "--workers", str(workers), *_env_flags(env)]
    return Call(collect, dict(source=source, episodes=seeds, out=store, seed_start=SEED_BASE[key], workers=workers,
                              policy=policy, image_every=p.image_every, max_steps=max_steps, loader=load_policy,
                              env=env),
                tuple(cmd))


def motion_planning_demos(task: str, seeds: range, out: Path) -> None:
    """ManiSkill's motion-planning demonstrations of ``task`` on ``seeds`` into ``out.h5`` (kept if present)."""
    if out.with_suffix(".h5").is_file():
        return
    if not DEMOS_SCRIPT.is_file():
        raise UserError(f"ManiSkill's demonstrations are made by scripts/maniskill_demos.sh of a wamplan checkout, "
                        f"not found at {DEMOS_SCRIPT}; run reproduce from a source checkout")
    done = subprocess.run([str(DEMOS_SCRIPT), "--task", task, "--seeds", f"{seeds.start}-{seeds.stop - 1}",
                           "--out", str(out)])
    if done.returncode != 0:
        raise UserError(f"scripts/maniskill_demos.sh failed (exit {done.returncode}); its output above says why")


def _demo_stages(p: Preset, d: Path, workers: int, env: EnvConfig) -> list[Stage]:
    """Demonstrations by ManiSkill's motion planner, imported clean (``expert``) and replayed with noise (``noisy``)."""
    from wamplan.data.importer import import_maniskill

    n = max(p.expert, p.noisy)
    seeds = range(SEED_BASE["demos"], SEED_BASE["demos"] + 2 * n)
    task = env.task
    mp, flag = d / "mp", ["--task", task]
    common = dict(trajectory=mp.with_suffix(".h5"), task=task, env=env, workers=workers, image_every=p.image_every)

    def imported(store: str, count: int, noise: float) -> Call:
        return Call(import_maniskill, dict(common, out=d / store, limit=count, noise_std=noise),
                    ("data", "import", "--format", "maniskill", str(mp.with_suffix(".h5")), str(d / store),
                     "--episodes", str(count), *(["--noise-std", str(noise)] if noise else []), "--image-every",
                     str(p.image_every), "--workers", str(workers), *flag, *_camera_flag(env)))

    return [Stage("demonstrations", (Call(motion_planning_demos, dict(task=task, seeds=seeds, out=mp),
                                          ("scripts/maniskill_demos.sh", *flag, "--seeds",
                                           f"{seeds.start}-{seeds.stop - 1}", "--out", str(mp))),)),
            Stage("import demonstrations", (imported("expert", p.expert, 0.0),)),
            Stage("import noisy", (imported("noisy", p.noisy, DEMO_NOISE),))]


def evaluate_conditions(conditions: list[int], episodes: int, out: Path, workers: int, wam: str, wm_plain: str,
                        wm_augmented: str, env: EnvConfig = EnvConfig()) -> dict[int, dict[str, int]]:
    """``wamplan eval`` for ``conditions`` on seeds 0 .. episodes-1 (resumable) with the paper's planner (CEM, not
    wamplan's default) in ``env``; outcome counts of new episodes."""
    from collections import Counter

    from wamplan.evaluation.config import EvalConfig
    from wamplan.evaluation.runner import run_evaluation

    cfg = EvalConfig(wam=wam, wm_plain=wm_plain, wm_augmented=wm_augmented, planner=PAPER_PLANNER,
                     env=env)
    cfg.check_for(conditions)
    counts: dict[int, Counter] = {c: Counter() for c in conditions}
    for rec in run_evaluation(cfg, conditions, list(range(episodes)), out, workers=workers):
        counts[rec["condition"]][rec["outcome"]] += 1
        print(f"cond {rec['condition']} seed {rec['seed']:4d} {rec['outcome']:22s} len {rec['length']:3d} "
              f"{rec['wall_time_s']:.0f}s", flush=True)
    return {c: dict(v) for c, v in counts.items() if v}


def plan(p: Preset, out: Path, wam: str | None, workers: int, sim_episodes: int | None = None,
         task: str = EnvConfig.task, camera_size: int = EnvConfig.camera_size) -> list[Stage]:
    """Every stage of the pipeline in ``task``, its cameras rendered at ``camera_size`` px; ``wam`` replaces TinyWAM
    training, ``sim_episodes`` the preset's count for the simulator conditions 2-5 (0 skips them)."""
    from wamplan.evaluation.report import write_report
    from wamplan.wam.train import train_tinywam
    from wamplan.worldmodel.stores import train_decoder_on_stores, train_predictor_on_stores

    spec = get_task(task)
    env = EnvConfig(task=task, camera_size=camera_size)  # every stage's env (validated here, before any work)
    if spec.expert is None and spec.demonstrations is None:
        raise UserError(f"reproduce starts from demonstrations, but task '{task}' has neither a scripted expert nor "
                        f"a source of demonstrations; collect its stores with `wamplan collect` or `wamplan data "
                        f"import` and run the later stages by hand")

    d, runs = out / "data", out / "runs"
    sim_episodes = p.sim_eval_episodes if sim_episodes is None else sim_episodes
    wam_ckpt = wam or str(runs / "tinywam")
    plain = [d / s for s in ("expert", "noisy", "pink")]
    aug = [*plain, d / "on_policy"]
    wm = p.world_model
    enc = dict(encoder=wm.encoder, encoder_kwargs=wm.encoder_kwargs)
    joined = lambda stores: ",".join(str(s) for s in stores)  # noqa: E731

    def wm_train(stores: list[Path], run: Path) -> Call:
        return Call(train_predictor_on_stores, dict(stores=stores, out=run, predictor=wm.predictor, train=wm.train, **enc),
                    ("wm", "train", "--data", joined(stores), "--out", str(run), "--preset", p.name))

    models = dict(wam=wam_ckpt, wm_plain=str(runs / "wm_plain"), wm_augmented=str(runs / "wm_augmented"))
    model_flags = ["--wam", wam_ckpt, "--wm-plain", models["wm_plain"], "--wm-augmented", models["wm_augmented"]]

    def evaluation(conds: list[int], episodes: int) -> Call:
        return Call(evaluate_conditions, dict(conditions=conds, episodes=episodes, out=out / "eval", workers=workers,
                                              env=env, **models),
                    ("eval", "--conditions", ",".join(map(str, conds)), "--episodes", str(episodes), "--out",
                     str(out / "eval"), *model_flags, "--planner", PAPER_PLANNER, "--workers", str(workers),
                     *_env_flags(env)))

    if spec.expert is None:
        out_stages = _demo_stages(p, d, workers, env)
        demo_source = "demo"
    else:
        out_stages = [Stage("collect expert", (_collect("expert", p, d / "expert", workers, p.expert, env=env),)),
                      Stage("collect noisy", (_collect("noisy-expert", p, d / "noisy", workers, p.noisy, env=env),))]
        demo_source = "expert"
    out_stages += [
        Stage("collect pink", (_collect("pink", p, d / "pink", workers, p.pink, max_steps=p.pink_max_steps,
                                        env=env),)),
    ]
    if wam is None:
        out_stages.append(Stage("train TinyWAM", (Call(
            train_tinywam, dict(stores=[d / "expert"], out=wam_ckpt, model_cfg=p.tinywam, train_cfg=p.tinywam_train,
                                sources=[demo_source]),
            ("wam", "train", "--data", str(d / "expert"), "--out", wam_ckpt, "--sources", demo_source, "--epochs",
             str(p.tinywam_train.epochs))),)))
    dec_stores = [d / s for s in p.decoder_sources]
    out_stages += [
        Stage("collect on-policy", (_collect("policy", p, d / "on_policy", workers, p.on_policy, policy=wam_ckpt,
                                             env=env),)),
        Stage("train plain world model", (wm_train(plain, runs / "wm_plain"),)),
        Stage("train augmented world model", (wm_train(aug, runs / "wm_augmented"),)),
        Stage("train decoder", (Call(train_decoder_on_stores, dict(stores=dec_stores, out=runs / "decoder",
                                                                   decoder=wm.decoder, train=wm.decoder_train, **enc),
                                     ("wm", "train-decoder", "--data", joined(dec_stores), "--out", str(runs / "decoder"),
                                      "--preset", p.name)),)),
        Stage("evaluate", (evaluation([1, 6, 7], p.eval_episodes),
                           *((evaluation([2, 3, 4, 5] if spec.expert else [5], sim_episodes),) if sim_episodes
                             else ()))),
        Stage("report", (Call(write_report, dict(out_dir=out / "eval"), ("report", str(out / "eval"))),)),
    ]
    return out_stages


def stages(p: Preset, out: Path, wam: str | None, workers: int, sim_episodes: int | None = None,
           task: str = EnvConfig.task, camera_size: int = EnvConfig.camera_size) -> list[tuple[str, list[list[str]]]]:
    """The ``wamplan`` command lines equivalent to every stage of :func:`plan` (what reproduce prints)."""
    return [(s.name, [list(c.command) for c in s.calls])
            for s in plan(p, out, wam, workers, sim_episodes, task, camera_size)]


def check_inputs(p: Preset, out: Path, wam: str | None, task: str) -> None:
    """One line, before the first stage of a run of hours, for what would fail later: ``out`` another kind of
    directory (a checkpoint, a store) or not writable, ``wam`` missing, not a WAM or made for another task, and
    the preset's encoder unbuildable (a pretrained one's weights absent)."""
    from wamplan.errors import require_own_dir, require_writable
    from wamplan.worldmodel.stores import frozen_encoder

    require_own_dir(out, (TIMES_FILE, "data"), "a reproduce directory")  # data/: its first stage under way
    require_writable(out)
    if wam is not None:
        from wamplan.envs.spec import check_same_task
        from wamplan.planning.dynamics import task_name
        from wamplan.wam import load_wam

        model = load_wam(wam, device="cpu")
        try:
            check_same_task(task, task_name(model), f"--wam {wam}")
        finally:
            model.close()
    try:
        frozen_encoder(p.world_model.encoder, p.world_model.encoder_kwargs, device="cpu")
    except UserError as e:  # reproduce has no --encoder-path: the weights come through the environment variable
        raise UserError(f"--preset {p.name}: {str(e).replace('pass --encoder-path DIR or set', 'set')}") from None


def reproduce(preset: str, out: Path, wam: str | None = None, workers: int = 1,
              sim_episodes: int | None = None, task: str = EnvConfig.task,
              camera_size: int = EnvConfig.camera_size) -> dict[str, float]:
    """Run every stage not yet finished, in order, in ``task`` (cameras at ``camera_size`` px); returns seconds per
    stage (kept in ``out/stage_times.json``)."""
    p = get_preset(preset)
    # a task or a size that cannot run fails here, before any work
    stage_list = plan(p, out, wam, workers, sim_episodes, task, camera_size)
    check_inputs(p, out, wam, task)
    out.mkdir(parents=True, exist_ok=True)
    times_path = out / TIMES_FILE
    times: dict[str, float] = json.loads(times_path.read_text()) if times_path.is_file() else {}
    for stage in stage_list:
        if stage.name in times:
            print(f"== {stage.name}: done ({times[stage.name] / 60:.1f} min; delete its entry in {times_path} to "
                  f"run it again)", flush=True)
            continue
        t0 = time.perf_counter()
        print(f"== {stage.name}", flush=True)
        for call in stage.calls:
            print("   " + call.line(), flush=True)
            try:
                call()
            except UserError as e:
                raise UserError(f"stage '{stage.name}' failed ({e}); fix it and re-run `wamplan reproduce` to "
                                f"resume") from e
        times[stage.name] = round(time.perf_counter() - t0, 1)
        times_path.write_text(json.dumps(times, indent=1) + "\n")
    for name, s in times.items():
        print(f"{name:30s} {s / 60:7.1f} min")
    return times
