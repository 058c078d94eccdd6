"""How well world models rank sibling chunks for a planner, per phase of the task: leave-one-out on branch groups.

    python scripts/wm_ranking.py checkpoints/mini/wm_augmented checkpoints/candidates/wm_dct_sib4_e8_cpu \
        --data data/wm_bench [--json ranking.json]

For every branch group of the stores, each sibling's true outcome K frames on is in turn the target, and the other
siblings are ranked by the distance of their predicted outcome to it, as the planner ranks candidates against the
WAM's predicted images (`worldmodel.train.sibling_ranking`). Per checkpoint and phase: ``rank_rho`` (Spearman's rho
of the predicted and true orders), ``rank_regret`` (0 = picks the best sibling, 1 = no better than chance) and
``rank_top1``; then the same with the predictions' group mean replaced by the true one (``*_sib``): how the ranking
would be if only the error the siblings share were removed. ``sib_rel_hK`` scores only the latter part.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from wamplan.errors import UserError
from wamplan.worldmodel.benchmark import ALL, PHASES, in_phase, load_benchmark
from wamplan.worldmodel.train import RANKING, sibling_ranking


def ranking_table(ckpt: str, data: list[Path], horizon: int) -> dict[str, dict[str, float]]:
    """phase (then "all") -> every figure of `sibling_ranking`, the mean over that phase's groups, and ``groups``."""
    model, groups, labels, _ = load_benchmark(ckpt, data, horizon)
    r = sibling_ranking(model, groups, horizon)
    out = {}
    for phase in (*PHASES, ALL):
        idx = in_phase(labels, phase)
        if idx:
            out[phase] = {"groups": len(idx), **{k: float(v[idx].mean()) for k, v in r.items()}}
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("ckpt", nargs="+", help="predictor checkpoints or run directories")
    ap.add_argument("--data", required=True, help="episode stores with branch groups, comma separated")
    ap.add_argument("--horizon", type=int, default=4)
    ap.add_argument("--json", type=Path, default=None, help="also write every figure to this JSON file")
    args = ap.parse_args()
    data = [Path(d) for d in args.data.split(",") if d]
    tables = {}
    try:
        for c in args.ckpt:
            tables[c] = ranking_table(c, data, args.horizon)
    except UserError as e:
        print(f"wm_ranking: {e}", file=sys.stderr)
        return 2
    print("each cell: rho / regret / top-1 as the model predicts | the same with the siblings' shared error removed")
    for ckpt, table in tables.items():
        print(f"\n{ckpt}\n| phase | groups | model | shared error removed |\n|---|---|---|---|")
        for phase, row in table.items():
            full = " / ".join(f"{row[k]:.2f}" for k in RANKING)
            sib = " / ".join(f"{row[k + '_sib']:.2f}" for k in RANKING)
            print(f"| {phase} | {row['groups']} | {full} | {sib} |")
    if args.json:
        args.json.write_text(json.dumps(tables, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
