"""The boundary model's data-scale curve: condition 7's success (95 % Wilson interval) and the held-out one-chunk
error against the number of on-policy parents, log scale, from data_scale.json (the measured points).

    python lab/boundary-history/plot_data_scale.py      # -> lab/boundary-history/figures/data_scale.png"""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from wamplan.evaluation.report import wilson  # noqa: E402

HERE = Path(__file__).parent


def main() -> Path:
    d = json.loads((HERE / "data_scale.json").read_text())
    pts = d["levels"]
    x = [p["parents"] for p in pts]
    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.4))
    for p in pts:
        lo, hi = wilson(p["success"], p["episodes"])
        r = p["success"] / p["episodes"]
        a.errorbar(p["parents"], 100 * r, yerr=[[100 * (r - lo)], [100 * (hi - r)]], fmt="o", color="C0", capsize=4)
    for (label, (k, n)), c in zip(d["reference"].items(), ("C7", "C2")):
        a.axhline(100 * k / n, color=c, ls="--", lw=1, label=f"{label}: {k}/{n}")
    a.set(xscale="log", xlabel="on-policy parents (6 branches a boundary)", ylabel="condition 7 success (%)",
          ylim=(0, 70), title="closed loop, validation 600-649")
    a.set_xticks(x, [str(v) for v in x])
    a.minorticks_off()
    a.legend(fontsize=7, loc="upper left")
    b.plot(x, [p["z_mse_h1"] for p in pts], "o-", label="held-out z_mse, one chunk")
    b.plot(x, [p["sib_gain_h1"] for p in pts], "s-", label="sib_gain (0: ignores the chunk)")
    b.set(xscale="log", xlabel="on-policy parents", title="offline, val split of parents 1+2")
    b.set_xticks(x, [str(v) for v in x])
    b.minorticks_off()
    b.legend(fontsize=7)
    fig.tight_layout()
    out = HERE / "figures" / "data_scale.png"
    fig.savefig(out, dpi=110)
    return out


if __name__ == "__main__":
    print(main())
