"""Two evaluation directories' runs of one condition, paired seed by seed: each run's success with its 95 % Wilson
interval, its outcomes and its mean search time a planned chunk; the seeds one gained and lost against the other
with the exact sign test; and how the changed seeds' outcomes moved.

    python lab/tools/compare_runs.py runs/s65/val_fg runs/s65/val_plain [--condition 7]

Only the seeds both directories hold count. The first directory is A, the second B ("A gained": A succeeded where
B failed).
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

from wamplan.evaluation.records import read_records
from wamplan.evaluation.report import sign_test, wilson


def by_seed(path: str, condition: int) -> dict[int, dict]:
    records = {r["seed"]: r for r in read_records(path) if r["condition"] == condition}
    if not records:
        sys.exit(f"error: {path} holds no finished episode of condition {condition}; pass an evaluation directory "
                 f"that ran it (`wamplan eval --conditions {condition} --out DIR`)")
    return records


def search_s(records: list[dict]) -> float:
    """The mean search time of the planned chunks (s; nan when none was planned)."""
    times = [c["search_s"] for r in records for c in r.get("chunks", []) if c.get("planned") and "search_s" in c]
    return sum(times) / len(times) if times else float("nan")


def compare(a: dict[int, dict], b: dict[int, dict]) -> dict:
    seeds = sorted(set(a) & set(b))
    if not seeds:
        sys.exit("error: the two directories share no seed of this condition; run them on the same seeds")
    out = {"seeds": len(seeds), "runs": []}
    for runs in (a, b):
        k = sum(bool(runs[s]["success"]) for s in seeds)
        out["runs"].append({"success": k, "ci": wilson(k, len(seeds)),
                            "outcomes": dict(Counter(runs[s]["outcome"] for s in seeds).most_common()),
                            "search_s": search_s([runs[s] for s in seeds])})
    gained = sum(bool(a[s]["success"]) and not b[s]["success"] for s in seeds)
    lost = sum(bool(b[s]["success"]) and not a[s]["success"] for s in seeds)
    moves = Counter((b[s]["outcome"], a[s]["outcome"]) for s in seeds if a[s]["outcome"] != b[s]["outcome"])
    out.update(gained=gained, lost=lost, p=sign_test(gained, lost), moves=moves.most_common())
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    p.add_argument("a", help="evaluation directory A")
    p.add_argument("b", help="evaluation directory B, the reference")
    p.add_argument("--condition", type=int, default=7)
    args = p.parse_args()
    for path in (args.a, args.b):
        if not Path(path).is_dir():
            sys.exit(f"error: {path} is not a directory; pass two evaluation directories")
    r = compare(by_seed(args.a, args.condition), by_seed(args.b, args.condition))
    n = r["seeds"]
    for name, run in zip((args.a, args.b), r["runs"]):
        lo, hi = run["ci"]
        print(f"{name}: {run['success']}/{n} = {100 * run['success'] / n:.0f} % ({100 * lo:.0f}-{100 * hi:.0f}), "
              f"search {run['search_s']:.2f} s a chunk; {run['outcomes']}")
    print(f"A gained {r['gained']} / lost {r['lost']} seeds against B, sign test p = {r['p']:.3f}")
    print("changed outcomes (B -> A): " + ", ".join(f"{x} -> {y} {k}" for (x, y), k in r["moves"]))


if __name__ == "__main__":
    main()
