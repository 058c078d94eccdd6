"""``wamplan eval`` and ``wamplan report``."""

from __future__ import annotations

import argparse
import json
import sys
import typing
from collections import Counter
from pathlib import Path

from wamplan.cli.main import add_command, first_screen, register_command
from wamplan.config import choices_metavar


@register_command("evaluation")
def register(sub: argparse._SubParsersAction) -> None:
    add_command(sub, "eval", _eval_options, help="run the paper's evaluation conditions (resumable, parallel)")
    add_command(sub, "reproduce", _reproduce_options,
                help="the whole pipeline: data, TinyWAM, world models, evaluation, report")
    add_command(sub, "gate-calibrate", _gate_calibrate_options,
                help="seed-cost quantiles of an always-planning evaluation, to choose --gate-threshold on held-out "
                     "episodes")
    add_command(sub, "explain", _explain_options,
                help="one planned chunk in pictures: the WAM's target, the world model's prediction under the WAM's "
                     "chunk and under the plan, and the real frames after each")
    add_command(sub, "film", _film_options,
                help="two conditions of an evaluation on the same seed in one video, for the seeds one solved and the "
                     "other did not (re-running episodes the evaluation did not film)")
    add_command(sub, "report", _report_options,
                help="Table 1, Figure 3 (and Table 2, timings) from an evaluation directory")


def _eval_options(p: argparse.ArgumentParser) -> None:
    from wamplan.cli.eval_options import add_eval_arguments
    from wamplan.parallel import add_backend_argument

    p.add_argument("--conditions", default="1,6,7", help="e.g. 1,6,7 or 1-7 (paper §4; default: 1,6,7)")
    p.add_argument("--episodes", type=int, default=50, help="episodes per condition: seeds --seed-start .. "
                                                           "--seed-start + N - 1 (default: 50)")
    p.add_argument("--seed-start", type=int, default=0, help="the first episode seed (default: 0; the test seeds "
                                                            "start at 0, keep validation seeds apart)")
    p.add_argument("--out", type=Path, required=True, help="evaluation directory: records.jsonl and eval_config.json "
                                                          "(created; re-running the same command resumes it)")
    p.add_argument("--workers", type=int, default=1, help="worker processes, or Ray actors with --ray (default: 1)")
    add_backend_argument(p)
    add_eval_arguments(p)
    add_video_arguments(p)
    first_screen(p, "--conditions", "--episodes", "--seed-start", "--workers", "--wam", "--wam-url", "--wm-plain",
                 "--wm-augmented", "--device", "--planner", "--task", "--camera-size")
    p.set_defaults(func=cmd_eval)


def add_video_arguments(p: argparse.ArgumentParser) -> None:
    """``--videos``, ``--video-every``, ``--video-size``, ``--decoder``: what is filmed into OUT/videos, and how."""
    from wamplan.config import add_arguments
    from wamplan.evaluation.videos import VideoConfig

    add_arguments(p.add_argument_group("videos"), VideoConfig)


def _reproduce_options(p: argparse.ArgumentParser) -> None:
    from wamplan.envs.config import EnvConfig
    from wamplan.envs.spec import TASKS
    from wamplan.presets import PRESETS

    p.add_argument("--preset", default="mini", choices=sorted(PRESETS),
                   help="mini (this CPU machine) or paper (default: mini)")
    p.add_argument("--out", type=Path, required=True, help="directory for every stage's outputs (re-running resumes)")
    p.add_argument("--wam", default=None, help="use this WAM checkpoint instead of training TinyWAM")
    p.add_argument("--workers", type=int, default=1, help="worker processes for collection and evaluation (default: 1)")
    p.add_argument("--sim-episodes", type=int, default=None,
                   help="episodes for the simulator conditions 2-5 (default: the preset's; 0 skips them)")
    p.add_argument("--task", default=EnvConfig.task, metavar=choices_metavar(sorted(TASKS)),  # checked by reproduce
                   help=f"the registered task every stage runs in; it needs a scripted expert or ManiSkill's "
                        f"motion-planning demonstrations (then conditions 2-4 are left out) (default: {EnvConfig.task})")
    p.add_argument("--camera-size", type=int, default=EnvConfig.camera_size,
                   help=f"rendered image side in pixels, every camera, in every stage that makes an env "
                        f"(default: {EnvConfig.camera_size})")
    p.set_defaults(func=cmd_reproduce)


def _gate_calibrate_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("dir", type=Path, help="an evaluation directory of always-planning runs (`wamplan eval --out`)")
    p.add_argument("--quantiles", type=float, nargs="+", default=[0.1, 0.25, 0.4, 0.5, 0.6, 0.75, 0.9],
                   help="quantiles of the per-chunk seed cost to print (default: 0.1 0.25 0.4 0.5 0.6 0.75 0.9)")
    p.set_defaults(func=cmd_gate_calibrate)


def _explain_options(p: argparse.ArgumentParser) -> None:
    from wamplan.cli.eval_options import add_eval_arguments

    p.add_argument("--seed", type=int, default=0, help="episode seed (condition 7 runs up to the chunk) (default: 0)")
    p.add_argument("--chunk", type=int, default=4,
                   help="chunk index to explain (>= 1; chunk k starts at step 16k) (default: 4)")
    p.add_argument("--decoder", required=True, help="picture decoder checkpoint (`wamplan wm train-decoder`)")
    p.add_argument("--out", type=Path, default=Path("mechanism.png"), help="PNG to write (default: mechanism.png)")
    add_eval_arguments(p)
    p.set_defaults(func=cmd_explain)


FILM_FIELDS = ("video_every", "video_size", "decoder")  # the VideoConfig fields `wamplan film` takes


def _film_options(p: argparse.ArgumentParser) -> None:
    from wamplan.config import add_field_argument
    from wamplan.evaluation.videos import VideoConfig

    p.add_argument("run", type=Path, help="an evaluation directory (`wamplan eval --out`); the videos go to "
                                          "RUN/videos/pairs/seed{seed:04d}_c{a}_vs_c{b}.webm")
    p.add_argument("--pair", default="1,7", help="the two conditions, top one first (default: 1,7)")
    p.add_argument("--seeds", default=None, help="seeds to film, e.g. 0-3,9 (default: those one condition solved and "
                                                 "the other did not)")
    p.add_argument("--first-chunk", default="open-loop", help="the records' first-chunk variant (default: open-loop)")
    p.add_argument("--device", default="auto", help="torch device for the episodes re-run (default: auto)")
    hints = typing.get_type_hints(VideoConfig)
    for name in FILM_FIELDS:  # how an episode the run did not film is filmed
        add_field_argument(p, "--" + name.replace("_", "-"), name, VideoConfig.__dataclass_fields__[name], hints[name])
    p.set_defaults(func=cmd_film)


def cmd_film(args: argparse.Namespace) -> int:
    from wamplan.config import int_list
    from wamplan.envs.media import require_webm
    from wamplan.errors import UserError
    from wamplan.evaluation.conditions import CONDITIONS
    from wamplan.evaluation.pairs import disagreeing_seeds, film_pairs, paired_records
    from wamplan.evaluation.records import RECORDS, no_records, read_records
    from wamplan.evaluation.videos import VideoConfig, plan_video_note, require_video_dir

    pair = int_list(args.pair, "--pair", example="1,7")
    if len(pair) != 2 or pair[0] == pair[1] or not all(c in CONDITIONS for c in pair):
        raise UserError(f"--pair {args.pair}: name two different conditions of 1-7, e.g. 1,7")
    a, b = pair
    if not (args.run / RECORDS).is_file():
        raise UserError(no_records(args.run))
    videos = VideoConfig(videos="all", **{k: getattr(args, k) for k in FILM_FIELDS if getattr(args, k) is not None})
    require_webm()
    require_video_dir(args.run)
    records = read_records(args.run)
    both = paired_records(records, a, b, args.first_chunk)
    if args.seeds is None:
        seeds = disagreeing_seeds(records, a, b, args.first_chunk)
        if not seeds:
            print(f"conditions {a} and {b} agree on all {len(both)} seeds they share in {args.run}: nothing to film "
                  f"(pass --seeds to film some anyway)")
            return 0
    else:
        seeds = int_list(args.seeds, "--seeds")
        missing = [s for s in seeds if s not in both]
        if missing:
            raise UserError(f"--seeds: {args.run} holds no records of both conditions {a} and {b} for seeds "
                            f"{missing[:8]}; pick seeds both ran")
    print(f"filming {len(seeds)} seeds, condition {a} above condition {b}")
    done, differed, noted = [], 0, False
    for f in film_pairs(args.run, a, b, seeds, videos, args.first_chunk, args.device):
        note = plan_video_note(videos, f.rerun) if f.rerun and not noted else None
        if note:  # once, for the first episode re-run of a planned condition
            print(note, file=sys.stderr)
            noted = True
        said = f" (re-ran condition{'s' if len(f.rerun) > 1 else ''} {', '.join(map(str, f.rerun))})" if f.rerun else ""
        print(f"seed {f.seed}: {a} {f.outcomes[a]} | {b} {f.outcomes[b]} -> {f.path}{said}")
        for c, (was, now) in f.differed.items():
            differed += 1
            print(f"warning: seed {f.seed} condition {c} re-ran to {now[0]} in {now[1]} steps, but its record says "
                  f"{was[0]} in {was[1]} steps (re-runs are identical only on the machine that made the run): its "
                  f"video shows the re-run", file=sys.stderr)
        done.append(f.seed)
    print(json.dumps({"pairs": len(done), "seeds": done, "reruns_differing": differed}))
    return 0


def _report_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("dir", type=Path, help="evaluation directory; the report is written there")
    p.add_argument("more", nargs="*", metavar="RUN", help="further evaluation directories whose records join DIR's "
                   "(e.g. conditions run apart on the same seeds), each DIR or DIR:C[,C...] for only those "
                   "conditions; DIR may then be a new, empty directory")
    p.set_defaults(func=cmd_report)


def _local_chunk_length(wam: str) -> int | None:
    """The chunk length a local WAM checkpoint records (None: not a local checkpoint, or none recorded)."""
    from wamplan.checkpoint import CheckpointError, checkpoint_dir, read_meta

    try:
        model = read_meta(checkpoint_dir(wam)).get("config", {}).get("model") if wam else None
    except (CheckpointError, OSError):
        return None
    return model.get("chunk_length") if isinstance(model, dict) else None


def cmd_explain(args: argparse.Namespace) -> int:
    from wamplan.device import resolve_device
    from wamplan.errors import UserError, require_file, require_paths, require_seeds
    from wamplan.evaluation.explain import explain_chunk
    from wamplan.evaluation.mechanism import mechanism_figure
    from wamplan.cli.eval_options import eval_config_from_args

    require_seeds(args.seed, flag="--seed")
    cfg = eval_config_from_args(args)
    resolve_device(cfg.device)
    cfg.check_for([7])
    require_paths([args.decoder], "--decoder", "train one with `wamplan wm train-decoder`")
    require_file(args.out, "--out")
    spec = cfg.env.spec  # what can be refused before the episode runs: a chunk past the episode, a decoder's kind
    steps = cfg.env.max_episode_steps or spec.max_episode_steps
    chunk = _local_chunk_length(cfg.wam)  # None for a served WAM: then the episode tells
    last = -(-steps // chunk) - 1 if chunk else args.chunk
    if args.chunk > last:
        raise UserError(f"--chunk {args.chunk}: episodes of {spec.name} end by step {steps}, so with the WAM's "
                        f"{chunk}-step chunks the last is chunk {last}; pick --chunk 1..{last}")
    from wamplan.worldmodel.decoder import load_decoder

    load_decoder(args.decoder, task=spec.name)  # its kind and task
    m = explain_chunk(cfg, args.decoder, args.seed, args.chunk)
    title = (f"seed {args.seed}, chunk {args.chunk}: WAM {Path(cfg.wam).name}, world model "
             f"{Path(cfg.wm_augmented).name}, planner {cfg.planner}")
    mechanism_figure(m, args.out, title)
    print(json.dumps(dict(out=str(args.out), step=m.step, model_cost=m.model_cost, true_cost=m.true_cost,
                          cube_xy_mm=m.cube_xy_mm)))
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    from wamplan.cli.eval_options import eval_config_from_args
    from wamplan.config import from_args
    from wamplan.evaluation.videos import VIDEOS, VideoConfig, plan_video_note
    from wamplan.errors import require_dir, require_positive, require_seeds
    from wamplan.evaluation.conditions import parse_conditions
    from wamplan.evaluation.records import read_records, record_key
    from wamplan.parallel import Backend
    from wamplan.progress import progress_bar

    # every check that needs no torch first: a mistyped option is answered before torch loads
    backend = Backend.from_option(args.ray)
    conds = parse_conditions(args.conditions)
    require_positive(("--episodes", args.episodes), ("--workers", args.workers))
    require_seeds(args.seed_start, args.episodes)
    require_dir(args.out)
    cfg = eval_config_from_args(args)  # the env's settings (backends) are checked here, before any work
    cfg.check_for(conds)
    videos = from_args(VideoConfig, args)
    backend.check()
    from wamplan.device import resolve_device
    from wamplan.evaluation.runner import run_evaluation

    resolve_device(cfg.device)
    seeds = list(range(args.seed_start, args.seed_start + args.episodes))
    done = {record_key(r) for r in read_records(args.out)}
    total = len(conds) * len(seeds)
    have = sum((c, s, cfg.policy.first_chunk) in done for c in conds for s in seeds)
    counts: dict[int, Counter] = {c: Counter() for c in conds}
    records = run_evaluation(cfg, conds, seeds, args.out, workers=args.workers, backend=backend,
                             videos=videos)  # checks inputs, the video directory and codec
    if have:  # after the checks: a resume they refuse says only why
        print(f"resuming: {have} of {total} episodes already recorded in {args.out}")
    filmed = videos.filmed(seeds)
    if filmed and have < total:
        print(f"filming seeds {_seed_list(sorted(filmed))} of every condition into {args.out / VIDEOS}")
        note = plan_video_note(videos, conds, cfg.oracle_blend)
        if note:
            print(note, file=sys.stderr)
    bar = progress_bar(total=total, initial=have, desc="eval", unit="ep")
    proxy: Counter = Counter()  # a planning proxy's chunks, by what it did (the WAM is one at --wam-url)
    for rec in records:
        counts[rec["condition"]][rec["outcome"]] += 1
        proxy.update(rec.get("proxy", {}))
        said = f" proxy planned {rec['proxy'].get('planned', 0)}/{sum(rec['proxy'].values())}" if "proxy" in rec else ""
        bar.update(1)
        bar.write(f"cond {rec['condition']} seed {rec['seed']:4d} {rec['outcome']:22s} len {rec['length']:3d} "
                  f"{rec['wall_time_s']:.0f}s{said}")
    bar.close()
    summary = {c: dict(v) for c, v in counts.items() if v}
    print(json.dumps({"new_episodes": summary}))
    if proxy and not proxy["planned"]:
        print(proxy_warning(proxy), file=sys.stderr)
    return 0


def _seed_list(seeds: list[int]) -> str:
    """0-3 for a run of consecutive seeds, else 0,5,9 (at most 8 shown)."""
    if seeds == list(range(seeds[0], seeds[-1] + 1)) and len(seeds) > 2:
        return f"{seeds[0]}-{seeds[-1]}"
    return ",".join(map(str, seeds[:8])) + (",..." if len(seeds) > 8 else "")


def proxy_warning(chunks: Counter) -> str:
    """One line for an evaluation through a planning proxy that planned none of ``chunks`` (reason -> count)."""
    why = ", ".join(f"{k} {v}" for k, v in chunks.most_common())
    hint = (" (no-history: its world model lacked the in-chunk frames; send them with --wam-send-chunk-frames at "
            "multiples of its frameskip, e.g. 4 8 12, as `wamplan serve`'s banner says)" if "no-history" in chunks
            else "")
    return f"warning: the planning proxy planned none of the {sum(chunks.values())} chunks it answered ({why}){hint}"


def cmd_report(args: argparse.Namespace) -> int:
    from wamplan.evaluation.report import write_report

    paths = write_report(args.dir, args.more)
    print((args.dir / "table1.md").read_text())
    print("wrote " + ", ".join(str(p) for p in paths.values()))
    return 0


def cmd_gate_calibrate(args: argparse.Namespace) -> int:
    from wamplan.errors import UserError
    from wamplan.evaluation.gate import gate_table
    from wamplan.evaluation.records import RECORDS, no_records

    odd = [q for q in args.quantiles if not 0 <= q <= 1]
    if odd:
        raise UserError(f"--quantiles {odd[0]:g}: quantiles lie in [0, 1], e.g. 0.25 for the lower quartile")
    if not (args.dir / RECORDS).is_file():
        raise UserError(no_records(args.dir))
    table = gate_table(args.dir, tuple(args.quantiles))
    if not table:
        raise UserError(f"{args.dir} holds no planned chunks with a seed_cost; run `wamplan eval` there first")
    for c, row in table.items():
        print(f"condition {c}: {row['chunks']} planned chunks, fraction planned {row['planned_fraction']:.2f}")
        for q, v in row["quantiles"].items():
            print(f"  --gate-threshold {v:.6g}  skips ~{q:.0%} of these chunks")
    return 0


def cmd_reproduce(args: argparse.Namespace) -> int:
    from wamplan.errors import require_dir
    from wamplan.evaluation.reproduce import reproduce

    require_dir(args.out)
    reproduce(args.preset, args.out, wam=args.wam, workers=args.workers, sim_episodes=args.sim_episodes,
              task=args.task, camera_size=args.camera_size)
    return 0
