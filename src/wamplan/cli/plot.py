"""``wamplan plot RUN``: the training curves of a run as a PNG."""

from __future__ import annotations

import argparse
from pathlib import Path

from wamplan.cli.main import add_command, register_command


@register_command("plot")
def register(sub: argparse._SubParsersAction) -> None:
    add_command(sub, "plot", _plot_options,
                help="draw a training run's curves (losses, validation, lr) from its metrics.jsonl")


def _plot_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", type=Path, help="run directory of `wamplan wm train` / `wamplan wam train` (or a metrics.jsonl)")
    p.add_argument("--out", type=Path, default=None, help="PNG to write (default: RUN/curves.png)")
    p.set_defaults(func=cmd_plot)


def cmd_plot(args: argparse.Namespace) -> int:
    from wamplan.errors import require_file
    from wamplan.plot import plot_training_curves

    out = args.out or (args.run if args.run.is_dir() else args.run.parent) / "curves.png"
    require_file(out, "--out" if args.out else "the plot (default --out)")
    print(f"wrote {plot_training_curves(args.run, out)}")
    return 0
