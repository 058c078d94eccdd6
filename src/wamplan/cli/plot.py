"""``wamplan plot RUN``: the training curves of a run as a PNG."""

from __future__ import annotations

import argparse
from pathlib import Path

from wamplan.cli.main import register_command


@register_command("plot")
def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("plot", help="draw a training run's curves (losses, validation, lr) from its metrics.jsonl")
    p.add_argument("run", type=Path, help="run directory of `wamplan wm train` / `wamplan wam train` (or a metrics.jsonl)")
    p.add_argument("--out", type=Path, default=None, help="PNG to write (default: RUN/curves.png)")
    p.set_defaults(func=cmd_plot)


def cmd_plot(args: argparse.Namespace) -> int:
    from wamplan.plot import plot_training_curves

    print(f"wrote {plot_training_curves(args.run, args.out)}")
    return 0
