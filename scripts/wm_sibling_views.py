"""Where the chunk's effect is seen, view by view: the sibling statistics of ``wamplan wm eval`` split by camera.

    python scripts/wm_sibling_views.py checkpoints/mini/wm_augmented runs/wm41/e4/adaln/checkpoint \
        --data data/wm_bench [--json views.json]

For each checkpoint, phase (grasp, carry, alignment, descent, all) and camera: ``share``, that view's part of how
much the sibling chunks' true outcomes differ (the spread, summed over the views = 1: where the world shows the
chunk's effect), and the model's ``sib_rel_hK`` / ``sib_gain_hK`` on that view alone (``wamplan wm eval``'s
definitions, `worldmodel/train.py`). A view with a large share and a low gain is where the model misses most.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from wamplan.data.features import feature_key
from wamplan.data.readers import BranchGroups
from wamplan.errors import UserError
from wamplan.worldmodel.benchmark import ALL, group_phases, pool_by_phase
from wamplan.worldmodel.stores import encode_stores, stores_task
from wamplan.worldmodel.train import load_world_model, sibling_statistics


def view_table(ckpt: str, data: list[Path], horizon: int) -> dict[str, dict[str, dict[str, float]]]:
    """phase -> camera -> {share, sib_rel_hK, sib_gain_hK} of one checkpoint on the stores ``data``."""
    model, enc = load_world_model(ckpt)
    _, cameras = stores_task(data)
    encode_stores(data, enc)
    groups = BranchGroups(data, model.cfg.frameskip, model.cfg.context, horizon, split="all",
                          features=feature_key(enc.config_dict()))
    if not len(groups):
        raise UserError(f"{', '.join(map(str, data))} holds no counterfactual branch groups: score a store "
                        f"collected with --branches (e.g. scripts/wm_benchmark_store.py)")
    labels = group_phases(groups)
    s = sibling_statistics(model, groups, horizon, per_view=True)  # each (G, K, V)
    views = [pool_by_phase({k: x[..., v] for k, x in s.items()}, labels, horizon) for v in range(len(cameras))]
    spread = s["spread"][:, -1]  # (G, V): how much the siblings' true outcomes differ, per view
    out: dict[str, dict[str, dict[str, float]]] = {}
    for phase in views[0]:  # the phases with groups, then "all"
        mine = spread[[i for i, p in enumerate(labels) if phase in (p, ALL)]].sum(0)  # (V,)
        out[phase] = {cam: {"share": float(mine[v] / mine.sum().clamp_min(1e-12)),
                            **{k: views[v][phase][k] for k in (f"sib_rel_h{horizon}", f"sib_gain_h{horizon}")}}
                      for v, cam in enumerate(cameras)}
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("ckpt", nargs="+", help="predictor checkpoints or run directories")
    ap.add_argument("--data", required=True, help="episode stores with branch groups, comma separated")
    ap.add_argument("--horizon", type=int, default=4)
    ap.add_argument("--json", type=Path, default=None, help="also write every figure to this JSON file")
    args = ap.parse_args()
    data = [Path(d) for d in args.data.split(",") if d]
    try:
        tables = {c: view_table(c, data, args.horizon) for c in args.ckpt}
    except UserError as e:
        print(f"wm_sibling_views: {e}", file=sys.stderr)
        return 2
    k = args.horizon
    print(f"each cell: share of the world's sibling spread / sib_rel_h{k} / sib_gain_h{k} of the model on that view")
    for ckpt, table in tables.items():
        cams = list(next(iter(table.values())))
        print(f"\n{ckpt}\n| phase | " + " | ".join(cams) + " |\n|---|" + "---|" * len(cams))
        for phase, row in table.items():
            print(f"| {phase} | " + " | ".join(f"{row[c]['share']:.2f} / {row[c][f'sib_rel_h{k}']:.2f} / "
                                            f"{row[c][f'sib_gain_h{k}']:.2f}" for c in cams) + " |")
    if args.json:
        args.json.write_text(json.dumps(tables, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
