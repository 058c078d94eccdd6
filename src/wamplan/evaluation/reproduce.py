"""``wamplan reproduce``: the paper's whole pipeline, stage by stage, each skipping what exists.

collect expert / noisy / pink -> train TinyWAM -> collect on-policy rollouts of it -> train the plain and
the augmented world models -> evaluate the conditions -> report. Every stage is itself resumable (the
stores, trainers and evaluation records are), so an interrupted run continues where it stopped.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from wamplan.errors import UserError


@dataclass(frozen=True)
class ReproducePreset:
    name: str
    expert: int
    noisy: int
    pink: int
    on_policy: int
    pink_max_steps: int
    image_every: int
    wam_epochs: int
    wm_preset: str
    wm_epochs: int  # world-model training epochs (the decoder keeps its preset's)
    decoder_sources: tuple[str, ...]  # the stores the picture decoder learns from (never used for planning)
    eval_episodes: int
    sim_eval_episodes: int  # the simulator conditions (2-5) are costly on a CPU


PRESETS = {
    # paper §4: 100 expert, 500 noisy, 500 pink-noise (42k frames: ~84 steps each), 500 on-policy; 50 episodes
    "paper": ReproducePreset("paper", expert=100, noisy=500, pink=500, on_policy=500, pink_max_steps=84, image_every=1,
                             wam_epochs=30, wm_preset="paper", wm_epochs=24,
                             decoder_sources=("expert", "noisy", "pink", "on_policy"), eval_episodes=50,
                             sim_eval_episodes=50),
    # this 2-core CPU machine: smaller datasets, the mini world model; the sizes the demo checkpoints were
    # made with (README "Demo checkpoints"): about 3 h of collection and training on 2 cores
    "mini": ReproducePreset("mini", expert=100, noisy=150, pink=150, on_policy=100, pink_max_steps=100, image_every=4,
                            wam_epochs=12, wm_preset="mini", wm_epochs=4, decoder_sources=("expert",), eval_episodes=50,
                            sim_eval_episodes=10),
}
SEED_BASE = {"expert": 1000, "noisy": 2000, "pink": 3000, "on_policy": 4000}  # evaluation uses seeds 0..49


def stages(p: ReproducePreset, out: Path, wam: str | None, workers: int,
           sim_episodes: int | None = None) -> list[tuple[str, list[list[str]]]]:
    """The CLI commands of every stage; ``sim_episodes`` overrides the preset's count for conditions 2-5."""
    d = out / "data"
    sim_episodes = p.sim_eval_episodes if sim_episodes is None else sim_episodes
    w = ["--workers", str(workers)]
    ie = ["--image-every", str(p.image_every)]
    wam_ckpt = wam or str(out / "runs" / "tinywam")
    plain = ",".join(str(d / s) for s in ("expert", "noisy", "pink"))
    aug = plain + "," + str(d / "on_policy")
    evals = [["eval", "--conditions", "1,6,7", "--episodes", str(p.eval_episodes), "--out", str(out / "eval"),
              "--wam", wam_ckpt, "--wm-plain", str(out / "runs" / "wm_plain"),
              "--wm-augmented", str(out / "runs" / "wm_augmented"), *w]]
    if sim_episodes:
        evals.append([*evals[0][:2], "2,3,4,5", "--episodes", str(sim_episodes), *evals[0][5:]])
    out_stages = [
        ("collect expert", [["collect", "--source", "expert", "--episodes", str(p.expert), "--seed-start",
                             str(SEED_BASE["expert"]), "--out", str(d / "expert"), *ie, *w]]),
        ("collect noisy", [["collect", "--source", "noisy-expert", "--episodes", str(p.noisy), "--seed-start",
                            str(SEED_BASE["noisy"]), "--out", str(d / "noisy"), *ie, *w]]),
        ("collect pink", [["collect", "--source", "pink", "--episodes", str(p.pink), "--seed-start",
                           str(SEED_BASE["pink"]), "--max-steps", str(p.pink_max_steps), "--out", str(d / "pink"), *ie,
                           *w]]),
    ]
    if wam is None:
        out_stages.append(("train TinyWAM", [["wam", "train", "--data", str(d / "expert"), "--out", wam_ckpt,
                                              "--sources", "expert", "--epochs", str(p.wam_epochs)]]))
    out_stages += [
        ("collect on-policy", [["collect", "--source", "policy", "--policy", wam_ckpt, "--episodes", str(p.on_policy),
                                "--seed-start", str(SEED_BASE["on_policy"]), "--out", str(d / "on_policy"), *ie, *w]]),
        ("train plain world model", [["wm", "train", "--data", plain, "--out", str(out / "runs" / "wm_plain"),
                                      "--preset", p.wm_preset, "--epochs", str(p.wm_epochs)]]),
        ("train augmented world model", [["wm", "train", "--data", aug, "--out", str(out / "runs" / "wm_augmented"),
                                          "--preset", p.wm_preset, "--epochs", str(p.wm_epochs)]]),
        ("train decoder", [["wm", "train-decoder", "--data", ",".join(str(d / s) for s in p.decoder_sources),
                            "--out", str(out / "runs" / "decoder"),
                            "--preset", p.wm_preset]]),
        ("evaluate", evals),
        ("report", [["report", str(out / "eval")]]),
    ]
    return out_stages


def reproduce(preset: str, out: Path, wam: str | None = None, workers: int = 1, sim_episodes: int | None = None,
              run: Callable[[list[str]], int] | None = None) -> dict[str, float]:
    """Run every stage in order; returns seconds per stage (also written to ``out/stage_times.json``)."""
    from wamplan.cli import main

    if preset not in PRESETS:
        raise UserError(f"unknown preset '{preset}'; choose one of {sorted(PRESETS)}")
    run = run or main
    out.mkdir(parents=True, exist_ok=True)
    times: dict[str, float] = {}
    for name, commands in stages(PRESETS[preset], out, wam, workers, sim_episodes):
        t0 = time.perf_counter()
        print(f"== {name}", flush=True)
        for argv in commands:
            rc = run(argv)
            if rc:
                raise UserError(f"stage '{name}' failed (wamplan {' '.join(argv)} exited {rc}); fix it and re-run "
                                f"`wamplan reproduce` to resume")
        times[name] = round(time.perf_counter() - t0, 1)
        (out / "stage_times.json").write_text(json.dumps(times, indent=1) + "\n")
    for name, s in times.items():
        print(f"{name:30s} {s / 60:7.1f} min")
    return times
