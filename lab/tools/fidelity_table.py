"""Merge `wamplan wm fidelity --json` files of one model set (e.g. seeds split over processes) and print one row per
model: its own plan's gain in the simulator, paired against the first model, with the ranking scores, the gains in the
model's own cost, the cube's xy change and the paired median with a sign test beside it.

    python lab/tools/fidelity_table.py runs/fid41/screen_500-505.json runs/fid41/screen_506-511.json [--markdown]
    python lab/tools/fidelity_table.py runs/fid41/descent.json --steps 128-160     # one phase's boundaries only

Every file must score the same models in the same order (the first is the reference of the paired column) with the
same candidate settings; a boundary (seed, step) found in two files is one error line.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path


def load(paths: list[Path]) -> tuple[list[dict], list[str], dict]:
    """(records, model labels, config) of the merged files."""
    records, labels, config, seen = [], None, None, set()
    for path in paths:
        if not path.is_file():
            sys.exit(f"error: {path} does not exist; pass files written by `wamplan wm fidelity --json`")
        out = json.loads(path.read_text())
        if not out.get("records"):
            sys.exit(f"error: {path} holds no scored boundaries; pass files written by `wamplan wm fidelity --json`")
        mine = list(out["records"][0]["models"])
        if labels is not None and mine != labels:
            sys.exit(f"error: {path} scores models {mine}, the first file {labels}; merge runs of one --wm list")
        cfg = {k: v for k, v in out["config"].items() if k != "boundaries"}
        if config is not None and cfg != config:
            sys.exit(f"error: {path} was scored with other settings ({cfg} against {config}); merge runs of one "
                     f"setting (the same --execute: open-loop and closed-loop states do not pool)")
        for r in out["records"]:
            key = (r["seed"], r["step"])
            if key in seen:
                sys.exit(f"error: seed {key[0]} step {key[1]} is in two files; merge runs of disjoint seeds")
            seen.add(key)
        records += out["records"]
        labels, config = mine, cfg
    return records, labels, config


def _paired(records: list[dict], lab: str, first: str, key: str) -> list[float]:
    """``key`` of ``lab`` minus ``key`` of ``first``, over the boundaries where both have it."""
    return [r["models"][lab][key] - r["models"][first][key] for r in records
            if key in r["models"][lab] and key in r["models"][first]]


def own_cost(records: list[dict], lab: str) -> str:
    """The model's plan gain and the best candidate's gain, both in the model's own encoder's cost (means, %):
    how much of what its own cost can reach among the candidates its plan gets."""
    plan = [r["models"][lab]["plan_gain"] for r in records if "plan_gain" in r["models"][lab]]
    best = [r["models"][lab]["best_gain"] for r in records]
    return f"{100 * statistics.mean(plan):+.2f} / {100 * statistics.mean(best):+.2f}" if plan else "—"


def xy_vs(records: list[dict], lab: str, first: str) -> str:
    """The change of the cube's xy distance to the hole under the model's plan minus under ``first``'s (mean ±
    SE over boundaries, mm; < 0: the plan ends nearer the hole), a yardstick no encoder defines."""
    d = _paired(records, lab, first, "plan_xy_change_mm")
    if len(d) < 2:
        return "—"
    return f"{statistics.mean(d):+.2f} ± {statistics.stdev(d) / len(d) ** 0.5:.2f}"


def wins_vs(records: list[dict], lab: str, first: str) -> str:
    """The median paired plan gain over ``first`` (points) and the boundaries where it is above and below, with
    the two-sided sign test: a reading of the paired column that one far-off boundary cannot swing."""
    from wamplan.evaluation.report import sign_test

    d = [100 * x for x in _paired(records, lab, first, "plan_gain_ref")]
    if not d:
        return "—"
    won, lost = sum(x > 0 for x in d), sum(x < 0 for x in d)
    return f"{statistics.median(d):+.2f}, {won}-{lost} (p = {sign_test(won, lost):.3f})"


def plot_by_step(summary: dict, drawn: list[str], first: str, out: Path) -> Path:
    """Each drawn model's paired plan gain over ``first`` per boundary step (mean ± SE), one line a model."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from wamplan.plot import save_figure

    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    for i, lab in enumerate(drawn):
        steps = sorted(summary[lab]["by_step"], key=int)
        rows = [summary[lab]["by_step"][s] for s in steps]
        x = [int(s) + (i - (len(drawn) - 1) / 2) * 1.5 for s in steps]  # a small offset keeps the bars apart
        ax.errorbar(x, [100 * r.get("plan_gain_ref_vs_first_mean", float("nan")) for r in rows],
                    yerr=[100 * r.get("plan_gain_ref_vs_first_se", float("nan")) for r in rows], marker="o",
                    capsize=3, label=lab)
    ax.axhline(0, color="grey", lw=0.8)
    ax.set_xlabel("chunk boundary (step)")
    ax.set_ylabel(f"plan gain minus {first}'s (points)")
    ax.set_title("the plan's true-cost gain in the simulator, paired per boundary", fontsize=9)
    ax.legend(fontsize=7)
    return save_figure(fig, out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("files", nargs="+", type=Path, help="fidelity JSON files (wamplan wm fidelity --json)")
    p.add_argument("--markdown", action="store_true", help="print a markdown table")
    p.add_argument("--plot", type=Path, default=None, metavar="PNG",
                   help="also draw each model's paired plan gain against the first model per boundary step")
    p.add_argument("--models", default="", help="comma-separated labels to draw (default: all but the first)")
    p.add_argument("--steps", default="", help="keep only the boundaries at these steps, e.g. 128-160 or 32,128 "
                                               "(default: all)")
    args = p.parse_args(argv)
    from wamplan.config import int_list
    from wamplan.errors import UserError
    from wamplan.evaluation.fidelity import FidelityConfig, summarize

    records, labels, config = load(args.files)
    if args.steps:
        try:
            keep = set(int_list(args.steps, "--steps"))
        except UserError as e:
            sys.exit(f"error: {e}")
        held = sorted({r["step"] for r in records})
        records = [r for r in records if r["step"] in keep]
        if not records:
            sys.exit(f"error: no scored boundary lies at --steps {args.steps}; the files hold steps {held}")
    cfg = FidelityConfig(num_candidates=config["num_candidates"], top_k=config["top_k"])
    summary = summarize(records, labels, cfg)
    if not all("plans" in summary[lab] for lab in labels):
        sys.exit("error: some models have no scored plans; run `wamplan wm fidelity` with --plan (with --execute "
                 "alone only the executing model's plans are scored)")
    seeds = sorted({r["seed"] for r in records})
    print(f"{len(records)} boundaries, seeds {seeds[0]}-{seeds[-1]} ({len(seeds)}), steps "
          f"{sorted({r['step'] for r in records})}; paired: minus {labels[0]}'s at the same boundaries")
    head = ["model", "plan gain (%)", f"paired vs {labels[0]}", "mean - 2 SE", "plan beats WAM", "Spearman med",
            "pick gain med", "own cost: plan / best (%)", f"cube xy vs {labels[0]} (mm)",
            f"paired median, wins-losses (sign p)"]
    rows = []
    for lab in labels:
        s = summary[lab]
        d, se = s.get("plan_gain_ref_vs_first_mean"), s.get("plan_gain_ref_vs_first_se")
        rows.append([lab, f"{100 * s['plan_gain_ref_mean']:+.2f} ± {100 * s['plan_gain_ref_se']:.2f}",
                     "—" if d is None else f"{100 * d:+.2f} ± {100 * se:.2f}",
                     "—" if d is None else f"{100 * (d - 2 * se):+.2f}", f"{s['plan_beats_wam']:.0%}",
                     f"{s['spearman_median']:.2f}", f"{100 * s['pick_gain_median']:+.1f}",
                     own_cost(records, lab), "—" if lab == labels[0] else xy_vs(records, lab, labels[0]),
                     "—" if lab == labels[0] else wins_vs(records, lab, labels[0])])
    if args.plot:
        drawn = [m for m in args.models.split(",") if m] or labels[1:]
        unknown = sorted(set(drawn) - set(labels))
        if unknown:
            sys.exit(f"error: --models {', '.join(unknown)} not among the files' models {labels}")
        print(f"wrote {plot_by_step(summary, drawn, labels[0], args.plot)}")
    if args.markdown:
        print("| " + " | ".join(head) + " |\n|" + "---|" * len(head))
        for r in rows:
            print("| " + " | ".join(r) + " |")
    else:
        widths = [max(len(str(x)) for x in col) for col in zip(head, *rows)]
        for r in [head, *rows]:
            print("  ".join(str(x).ljust(w) for x, w in zip(r, widths)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
