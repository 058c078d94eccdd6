"""How well world models rank sibling chunks for a planner, per phase of the task: leave-one-out on branch groups.

    python lab/wm-variants/wm_ranking.py checkpoints/mini/wm_augmented checkpoints/candidates/wm_dct_sib4_e8_cpu \
        --data data/wm_bench [--json ranking.json]

For every branch group of the stores, each sibling's true outcome K frames on is in turn the target, and the other
siblings are ranked by the distance of their predicted outcome to it, as the planner ranks candidates against the
WAM's predicted images (`worldmodel.siblings.sibling_ranking`). Per checkpoint and phase: ``rank_rho`` (Spearman's rho
of the predicted and true orders), ``rank_regret`` (0 = picks the best sibling, 1 = no better than chance) and
``rank_top1``; then the same with the predictions' group mean replaced by the true one (``*_sib``): how the ranking
would be if only the error the siblings share were removed. ``sib_rel_hK`` scores only the latter part.
``--wam CKPT`` ranks every group's siblings against that WAM's predicted views instead, queried on the group's
boundary observation (the parent's stored images and proprio at the branch step) and encoded with each model's
encoder: the planner's own target.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from wamplan.errors import UserError
from wamplan.wam.base import WAM, load_wam
from wamplan.wam.targets import check_target_wam, group_targets
from wamplan.worldmodel.benchmark import ALL, PHASES, benchmark_parser, in_phase, load_benchmark
from wamplan.worldmodel.siblings import RANKING, sibling_ranking


def ranking_table(ckpt: str, data: list[Path], horizon: int, wam: WAM | None = None) -> dict[str, dict[str, float]]:
    """phase (then "all") -> every figure of `sibling_ranking`, the mean over that phase's groups, and ``groups``."""
    model, encoder, groups, labels, cameras = load_benchmark(ckpt, data, horizon)
    targets = None
    if wam is not None:
        check_target_wam(wam, cameras, horizon * model.cfg.frameskip)
        targets = group_targets(wam, groups, encoder)
    r = sibling_ranking(model, groups, horizon, targets=targets)
    out = {}
    for phase in (*PHASES, ALL):
        idx = in_phase(labels, phase)
        if idx:
            out[phase] = {"groups": len(idx), **{k: float(v[idx].mean()) for k, v in r.items()}}
    return out


def main() -> int:
    ap = benchmark_parser(__doc__.split("\n\n")[0])
    ap.add_argument("--wam", default=None,
                    help="rank against this WAM checkpoint's predicted views (e.g. checkpoints/mini/tinywam)")
    ap.add_argument("--json", type=Path, default=None, help="also write every figure to this JSON file")
    args = ap.parse_args()
    data = args.data
    tables = {}
    try:
        wam = None if args.wam is None else load_wam(args.wam, device="cpu")
        for c in args.ckpt:
            tables[c] = ranking_table(c, data, args.horizon, wam)
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
