"""How well world models rank sibling chunks for a planner, per phase of the task: leave-one-out on branch groups.

    python scripts/wm_ranking.py checkpoints/mini/wm_augmented checkpoints/candidates/wm_dct_sib4_e8_cpu \
        --data data/wm_bench [--json ranking.json]

For every branch group of the stores, each sibling's true outcome K frames on is in turn the target, and the other
siblings are ranked by the distance of their predicted outcome to it, as the planner ranks candidates against the
WAM's predicted images (`worldmodel.train.sibling_ranking`). Per checkpoint and phase: ``rank_rho`` (Spearman's rho
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

import h5py
import numpy as np
import torch

from wamplan.data.readers import BranchGroups
from wamplan.encoders.base import FrozenEncoder
from wamplan.envs.spec import Observation
from wamplan.errors import UserError
from wamplan.wam.base import WAM, load_wam
from wamplan.worldmodel.benchmark import ALL, PHASES, benchmark_parser, in_phase, load_benchmark
from wamplan.worldmodel.train import RANKING, sibling_ranking


def wam_targets(wam: WAM, groups: BranchGroups, encoder: FrozenEncoder, cameras) -> torch.Tensor:
    """(G_total, V, N, D): the WAM's predicted views of each group's boundary, encoded (the planner's target)."""
    out = []
    for members in groups.items:
        e = groups.episodes[members[0][0]]
        boundary, start = e.branch_at  # type: ignore[misc]  # the parent's boundary, and its step at the branch's 0
        k = list(e.image_steps).index(boundary - start)  # the stored frame at the boundary
        with h5py.File(e.path, "r") as f:
            obs = Observation(step=boundary, proprio=f["proprio"][boundary - start],
                              images={c: f["images"][c][k] for c in cameras})
        pred = wam.predict(obs, wam.default_instruction)
        out.append(encoder.encode(np.stack([pred.images[c] for c in cameras])))  # (V, N, D)
    return torch.stack(out)


def ranking_table(ckpt: str, data: list[Path], horizon: int, wam: WAM | None = None) -> dict[str, dict[str, float]]:
    """phase (then "all") -> every figure of `sibling_ranking`, the mean over that phase's groups, and ``groups``."""
    model, encoder, groups, labels, cameras = load_benchmark(ckpt, data, horizon)
    targets = None
    if wam is not None:
        steps = horizon * model.cfg.frameskip
        if steps != wam.chunk_length:
            raise UserError(f"the siblings are scored {steps} steps on (--horizon {horizon} x frameskip "
                            f"{model.cfg.frameskip}) but the WAM predicts {wam.chunk_length} steps on; give --horizon "
                            f"{wam.chunk_length // model.cfg.frameskip}")
        missing = [c for c in cameras if c not in wam.cameras]
        if missing:
            raise UserError(f"the WAM predicts no view for the stores' cameras {missing}; use a WAM of this task")
        targets = wam_targets(wam, groups, encoder, cameras)
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
