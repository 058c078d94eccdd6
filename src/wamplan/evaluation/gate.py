"""Calibrate the planned policy's gate (``--gate-threshold``) on held-out episodes.

Every planned chunk's record keeps ``seed_cost``, the WAM's own chunk scored through the planning objective.
Run an always-planning evaluation on seeds kept apart from the test seeds, then read the quantiles here: a
threshold at the q-quantile skips the search on about a fraction q of those chunks (``--gate-threshold``, the
cheap ones). The fraction of chunks
planned in an evaluation is ``planned_chunks / (planned_chunks + sum(open_loop_chunks.values()))``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from wamplan.evaluation.records import read_records


def seed_costs(records: list[dict[str, Any]], condition: int) -> np.ndarray:
    """The seed costs (n,) of every planned chunk of ``condition``'s records."""
    return np.array([ch["seed_cost"] for r in records if r["condition"] == condition
                     for ch in r.get("chunks", []) if ch.get("planned") and np.isfinite(ch.get("seed_cost", np.nan))],
                    dtype=np.float64)


def planned_fraction(records: list[dict[str, Any]], condition: int) -> float:
    """Chunks whose plan was executed / all chunks of ``condition`` (open-loop first chunks, warm-up, gated and
    discarded ones included in the total)."""
    recs = [r for r in records if r["condition"] == condition]
    planned = sum(r.get("planned_chunks", 0) for r in recs)
    total = planned + sum(sum(r.get("open_loop_chunks", {}).values()) for r in recs)
    return planned / total if total else float("nan")


def gate_table(out_dir: str | Path, quantiles: tuple[float, ...] = (0.1, 0.25, 0.4, 0.5, 0.6, 0.75, 0.9)
               ) -> dict[int, dict[str, Any]]:
    """Per condition: the number of planned chunks, the fraction planned, and the seed-cost quantiles."""
    records = read_records(out_dir)
    out = {}
    for c in sorted({r["condition"] for r in records}):
        costs = seed_costs(records, c)
        if costs.size:
            out[c] = dict(chunks=int(costs.size), planned_fraction=planned_fraction(records, c),
                          quantiles={q: float(np.quantile(costs, q)) for q in quantiles})
    return out
