"""Where the chunk's effect is seen, view by view: the sibling statistics of ``wamplan wm eval`` split by camera.

    python lab/wm-variants/wm_sibling_views.py checkpoints/mini/wm_augmented runs/wm41/e4/adaln/checkpoint \
        --data data/wm_bench [--tokens descent] [--json views.json]

For each checkpoint, phase (grasp, carry, alignment, descent, all) and camera: ``share``, that view's part of how
much the sibling chunks' true outcomes differ (the spread, summed over the views = 1: where the world shows the
chunk's effect), and the model's ``sib_rel_hK`` / ``sib_gain_hK`` on that view alone (``wamplan wm eval``'s
definitions, `worldmodel/siblings.py`). A view with a large share and a low gain is where the model misses most.
``--tokens PHASE`` also prints, for that phase, each view's patch grid: every token's share of the spread (of all
views together) and the model's ``sib_gain_hK`` on that token alone. ``--bands PHASE`` prints, for that phase, the
model's figures on each view's first K feature dimensions only (``--band-dims``): with the low-pass encoder
(``{"basis": "dct"}``) the first K are a token's K/3 lowest frequencies (each in R, G and B), so the table says how well the model follows
the chunk's effect on the coarse picture and how much of the spread the finer detail holds.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import torch

from wamplan.errors import UserError
from wamplan.worldmodel.benchmark import ALL, PHASES, benchmark_parser, in_phase, load_benchmark, pool_by_phase
from wamplan.worldmodel.siblings import sibling_statistics


def split_statistics(ckpt: str, data: list[Path], horizon: int, per: str = "token"):
    """(statistics per token, each (G, K, V, N), or per feature, each (G, K, V, D); the groups' phase labels; the
    cameras) of one checkpoint."""
    model, _, groups, labels, cameras = load_benchmark(ckpt, data, horizon)
    return sibling_statistics(model, groups, horizon, per=per), labels, cameras


def view_table(s: dict[str, torch.Tensor], labels: list[str], cameras, horizon: int
               ) -> dict[str, dict[str, dict[str, float]]]:
    """phase -> camera -> {share, sib_rel_hK, sib_gain_hK} from the per-token statistics ``s``."""
    s = {k: x.mean(-1) for k, x in s.items()}  # (G, K, V): a view's figure is its tokens' mean (equal sizes)
    views = [pool_by_phase({k: x[..., v] for k, x in s.items()}, labels, horizon) for v in range(len(cameras))]
    spread = s["spread"][:, -1]  # (G, V): how much the siblings' true outcomes differ, per view
    out: dict[str, dict[str, dict[str, float]]] = {}
    for phase in views[0]:  # the phases with groups, then "all"
        mine = spread[in_phase(labels, phase)].sum(0)  # (V,)
        out[phase] = {cam: {"share": float(mine[v] / mine.sum().clamp_min(1e-12)),
                            **{k: views[v][phase][k] for k in (f"sib_rel_h{horizon}", f"sib_gain_h{horizon}")}}
                      for v, cam in enumerate(cameras)}
    return out


def token_grids(s: dict[str, torch.Tensor], labels: list[str], cameras, phase: str) -> dict[str, dict]:
    """camera -> {share, sib_gain}: (g, g) lists, row-major patch grid, of the groups in ``phase``."""
    idx = in_phase(labels, phase)
    if not idx:
        raise UserError(f"no branch group in phase {phase!r}; the store's phases: {', '.join(sorted(set(labels)))}")
    spread, cross = (s[k][idx, -1].sum(0) for k in ("spread", "cross"))  # (V, N)
    share, gain = spread / spread.sum().clamp_min(1e-12), cross / spread.clamp_min(1e-12)
    g = int(round(spread.shape[-1] ** 0.5))
    return {cam: {"share": share[v].view(g, g).tolist(), "sib_gain": gain[v].view(g, g).tolist()}
            for v, cam in enumerate(cameras)}


def band_table(s: dict[str, torch.Tensor], labels: list[str], cameras, phase: str, dims: list[int], horizon: int
               ) -> dict[int, dict[str, dict[str, float]]]:
    """K -> view (and "all") -> {share, sib_rel_hK, sib_gain_hK} on each view's first K features, from the per-feature
    statistics ``s`` (each (G, K, V, D)) of the groups in ``phase``; ``share`` is of the spread of every feature of
    every view."""
    idx = in_phase(labels, phase)
    if not idx:
        raise UserError(f"no branch group in phase {phase!r}; the store's phases: {', '.join(sorted(set(labels)))}")
    spread, err, cross = (s[k][idx, -1].sum(0) for k in ("spread", "err", "cross"))  # (V, D) each
    total = spread.sum().clamp_min(1e-12)
    out: dict[int, dict[str, dict[str, float]]] = {}
    for k in dims:
        parts = {cam: (slice(v, v + 1), slice(0, k)) for v, cam in enumerate(cameras)}
        parts[ALL] = (slice(None), slice(0, k))
        out[k] = {}
        for name, (vs, ds) in parts.items():
            sp = spread[vs, ds].sum().clamp_min(1e-12)
            out[k][name] = {"share": float(sp / total), f"sib_rel_h{horizon}": float(err[vs, ds].sum() / sp),
                            f"sib_gain_h{horizon}": float(cross[vs, ds].sum() / sp)}
    return out


def main() -> int:
    ap = benchmark_parser(__doc__.split("\n\n")[0])
    ap.add_argument("--tokens", default=None, choices=(*PHASES, ALL), metavar="PHASE",
                    help="also each view's patch grid at this phase (grasp, carry, alignment, descent, all)")
    ap.add_argument("--bands", default=None, choices=(*PHASES, ALL), metavar="PHASE",
                    help="also the figures on each view's first K features at this phase (K from --band-dims)")
    ap.add_argument("--band-dims", default="3,6,12,24,48,96",
                    help="comma-separated K for --bands; the encoder's full dimension is always added")
    ap.add_argument("--json", type=Path, default=None,
                    help="also write every figure to this JSON file ({views: ..., tokens: ..., bands: ...})")
    args = ap.parse_args()
    data = args.data
    try:
        dims = sorted({int(k) for k in args.band_dims.split(",") if k.strip()})
    except ValueError:
        print(f"wm_sibling_views: --band-dims must be whole numbers separated by commas, got {args.band_dims!r}",
              file=sys.stderr)
        return 2
    if not dims or dims[0] < 1:
        print(f"wm_sibling_views: --band-dims needs numbers >= 1, got {args.band_dims!r}", file=sys.stderr)
        return 2
    tables, grids, bands = {}, {}, {}
    try:
        for c in args.ckpt:
            s, labels, cameras = split_statistics(c, data, args.horizon)
            tables[c] = view_table(s, labels, cameras, args.horizon)
            if args.tokens:
                grids[c] = token_grids(s, labels, cameras, args.tokens)
            if args.bands:
                s, labels, cameras = split_statistics(c, data, args.horizon, per="feature")
                full = s["spread"].shape[-1]
                bands[c] = band_table(s, labels, cameras, args.bands, [k for k in dims if k < full] + [full],
                                      args.horizon)
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
    for ckpt, grid in grids.items():
        print(f"\n{ckpt}, {args.tokens}: each view's patch grid, every cell the token's share of the spread (all "
              f"views) / its sib_gain_h{k}")
        for cam, cells in grid.items():
            print(f"{cam}:")
            for shares, gains in zip(cells["share"], cells["sib_gain"]):
                print("  " + "  ".join(f"{a:.3f} / {b:+.2f}" for a, b in zip(shares, gains)))
    for ckpt, table in bands.items():
        cols = list(next(iter(table.values())))
        print(f"\n{ckpt}, {args.bands}: the figures on each view's first K features; each cell: share of the spread "
              f"(all features of all views) / sib_rel_h{k} / sib_gain_h{k}\n| K | " + " | ".join(cols) + " |\n|---|"
              + "---|" * len(cols))
        for dim, row in table.items():
            print(f"| {dim} | " + " | ".join(f"{row[c]['share']:.2f} / {row[c][f'sib_rel_h{k}']:.2f} / "
                                              f"{row[c][f'sib_gain_h{k}']:.2f}" for c in cols) + " |")
    if args.json:
        args.json.write_text(json.dumps({"views": tables, "tokens": grids, "bands": bands}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
