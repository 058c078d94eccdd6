"""Training curves of a run (``RUN/metrics.jsonl``, ``wamplan.train_loop``) as a PNG, and the figure writer every
picture of wamplan uses (``save_figure``).

Left: the training losses (``train/*``: per-step records as lines, epoch means as dots) and the
validation metrics (``val/*`` at epoch ends, dashed), on a log scale when all are positive.
Right: the learning rate. The x axis is the global optimisation step.
"""

from __future__ import annotations

from pathlib import Path

from wamplan.errors import UserError
from wamplan.train_loop import METRICS_FILE, read_metrics

# validation keys drawn by default: losses and MSEs, not the per-horizon breakdown or the baselines
_VAL_SKIP = ("copy_",)


def save_figure(fig, out: str | Path, dpi: int = 90) -> Path:
    """Lay out a matplotlib figure, write it to ``out`` (parents created) and close it."""
    import matplotlib.pyplot as plt

    out = Path(out)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=dpi)
    plt.close(fig)
    return out


def _val_keys(records: list[dict]) -> list[str]:
    keys = sorted({k for r in records for k in r if k.startswith("val/")})
    main = [k for k in keys if not any(k[4:].startswith(s) for s in _VAL_SKIP) and not k.rstrip("0123456789").endswith("_h")]
    return main or keys


def plot_training_curves(run: str | Path, out: str | Path | None = None) -> Path:
    """Draw the curves of the run directory (or metrics file) ``run``; returns the PNG path
    (default ``RUN/curves.png``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run = Path(run)
    records = read_metrics(run)
    if not records:
        raise UserError(f"{run} has no training metrics (no {METRICS_FILE} records); pass a run directory of "
                        f"`wamplan wm train` or `wamplan wam train`")
    steps = [r for r in records if r.get("event") == "step"]
    epochs = [r for r in records if r.get("event", "epoch") == "epoch"]
    out = Path(out) if out is not None else (run if run.is_dir() else run.parent) / "curves.png"

    fig, (ax, ax_lr) = plt.subplots(1, 2, figsize=(11, 4), gridspec_kw={"width_ratios": [3, 1]})
    train_keys = sorted({k for r in records for k in r if k.startswith("train/")})
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    values: list[float] = []
    for i, k in enumerate(train_keys):
        c = colours[i % len(colours)]
        pts = [(r["global_step"], r[k]) for r in steps if k in r]
        if pts:
            ax.plot(*zip(*pts), color=c, lw=1.2, label=k)
        ep = [(r["global_step"], r[k]) for r in epochs if k in r]
        if ep:
            ax.plot(*zip(*ep), "o", color=c, ms=4, label=None if pts else f"{k} (epoch mean)")
        values += [v for _, v in pts + ep]
    for j, k in enumerate(_val_keys(epochs)):
        pts = [(r["global_step"], r[k]) for r in epochs if k in r]
        ax.plot(*zip(*pts), "s--", color=colours[(len(train_keys) + j) % len(colours)], ms=4, lw=1.2, label=k)
        values += [v for _, v in pts]
    if values and min(values) > 0:
        ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss / metric")
    ax.set_title(f"{run.name if run.is_dir() else run.parent.name}: {len(epochs)} epochs, "
                 f"{max(r['global_step'] for r in records)} steps")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    lr = sorted({(r["global_step"], r["lr"]) for r in records if "lr" in r})
    if lr:
        ax_lr.plot(*zip(*lr), ".-", color="k", ms=3, lw=1)
    ax_lr.set_xlabel("step")
    ax_lr.set_title("learning rate")
    ax_lr.grid(alpha=0.3)
    return save_figure(fig, out, dpi=110)
