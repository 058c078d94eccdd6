"""Two `wamplan wm fidelity --json` runs of the same model on the same boundaries and candidates (e.g. the plain
cost and another as the yardstick), paired boundary by boundary: the mean difference (B - A, ± its standard error)
of the rank agreement, the top-k overlap and the pick gain; how alike the two runs' costs rank the candidates
(median Spearman of the simulator's costs, and of the model's); and how often the model picks the same candidate.

    python lab/tools/fidelity_pair.py fid_plain.json fid_fg.json [--model shipped]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys

from scipy.stats import spearmanr


def boundaries(path: str, model: str) -> dict[tuple[int, int], dict]:
    out = json.load(open(path))
    found = {(r["seed"], r["step"]): r["models"][model] for r in out.get("records", []) if model in r["models"]}
    if not found:
        sys.exit(f"error: {path} scores no boundary of model '{model}'; pass --model, one of its --wm labels")
    return found


def pair(a: dict, b: dict) -> dict:
    keys = sorted(set(a) & set(b))
    if len(keys) < 2:
        sys.exit("error: the two runs share fewer than 2 boundaries; run them on the same --seeds and --boundaries")
    if any(len(a[k]["true_costs"]) != len(b[k]["true_costs"]) for k in keys):
        sys.exit("error: the runs scored different numbers of candidates; run them with the same --candidates")
    out = {"boundaries": len(keys)}
    for name in ("spearman", "top_overlap", "pick_gain"):
        d = [b[k][name] - a[k][name] for k in keys]
        out[name] = (statistics.fmean(d), statistics.stdev(d) / len(d) ** 0.5)
    out["true_alike"] = statistics.median(spearmanr(a[k]["true_costs"], b[k]["true_costs"])[0] for k in keys)
    out["model_alike"] = statistics.median(spearmanr(a[k]["model_costs"], b[k]["model_costs"])[0] for k in keys)
    out["same_pick"] = statistics.fmean(a[k]["pick"] == b[k]["pick"] for k in keys)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    p.add_argument("a", help="the reference run's JSON")
    p.add_argument("b", help="the other run's JSON")
    p.add_argument("--model", default="shipped", help="the --wm label to pair (default: %(default)s)")
    args = p.parse_args()
    r = pair(boundaries(args.a, args.model), boundaries(args.b, args.model))
    print(f"{r['boundaries']} boundaries, B - A (mean ± SE):")
    for name in ("spearman", "top_overlap", "pick_gain"):
        print(f"  {name:12s} {r[name][0]:+.3f} ± {r[name][1]:.3f}")
    print(f"the two yardsticks rank the candidates alike: simulator {r['true_alike']:.2f}, model "
          f"{r['model_alike']:.2f} (median Spearman); the model picks the same candidate at {r['same_pick']:.0%} of "
          f"the boundaries")


if __name__ == "__main__":
    main()
