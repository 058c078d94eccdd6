"""The world-model variants table (issue 41) from ``wamplan wm eval --json`` reports on the benchmark store.

    .venv/bin/python lab/wm-variants/wm_variants_table.py runs/wm41/e4/*/bench.json

One row per report, named by its folder (``bench.json``) or by its folder and name (``NAME.bench.json``, as
for the variants of ``lab/wm-variants/wm_scale.py``): ``sib_rel_h4`` / ``sib_gain_h4`` for every phase, the latent error one
and four frames ahead (the ``all`` row: every group's siblings), the planning time per chunk that ``wm eval`` measured, and the
training time where ``lab/wm-variants/wm_variants.sh`` recorded it (``FOLDER.seconds``). Markdown on stdout.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def training_seconds(report: Path) -> str:
    """The training time ``lab/wm-variants/wm_variants.sh`` recorded beside the run (``RUN.seconds``, one line per attempt)."""
    log = report.parent.with_name(report.parent.name + ".seconds")
    lines = log.read_text().split() if log.is_file() else []
    return f"{sum(int(x) for x in lines) / 60:.0f} min" if lines and all(x.isdigit() for x in lines) else "—"


def label(report: Path) -> str:
    """``runs/x/adaln/bench.json`` -> ``adaln``; ``runs/x/gpu12/sib.bench.json`` -> ``gpu12/sib``."""
    stem = report.name.removesuffix(".json").removesuffix(".bench").removesuffix("bench")
    return f"{report.parent.name}/{stem}" if stem else report.parent.name


def row(name: str, r: dict, phases: list[str], k: int, train: str) -> str:
    cells = []
    for ph in phases:
        p = r["phases"].get(ph)
        cells.append(f"{p[f'sib_rel_h{k}']:.2f} / {p[f'sib_gain_h{k}']:.2f}" if p and p["groups"] else "—")
    pooled = r["phases"]["all"]
    return (f"| {name} | " + " | ".join(cells) + f" | {pooled['z_mse_h1']:.4f} / {pooled[f'z_mse_h{k}']:.4f} | "
            f"{r['plan_s_per_chunk']:.2f} | {train} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("reports", nargs="+", type=Path, help="bench.json files of `wamplan wm eval --json`")
    args = ap.parse_args()
    reports = {}
    for path in args.reports:
        try:
            r = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            print(f"error: cannot read {path} as a report ({e}); pass the files `wamplan wm eval --json` wrote",
                  file=sys.stderr)
            return 2
        if not isinstance(r, dict) or "phases" not in r:
            print(f"error: {path} has no per-phase figures; make it with `wamplan wm eval --data data/wm_bench "
                  f"--json` on a store with branches", file=sys.stderr)
            return 2
        reports[path] = r
    k = next(iter(reports.values()))["horizon"]
    phases = list(next(iter(reports.values()))["phases"])
    print(f"| variant | " + " | ".join(f"{ph}: sib_rel_h{k} / sib_gain_h{k}" for ph in phases)
          + f" | z_mse_h1 / z_mse_h{k} | plan s/chunk | training |")
    print("|---" * (len(phases) + 4) + "|")
    for path, r in reports.items():
        print(row(label(path), r, phases, k, training_seconds(path)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
