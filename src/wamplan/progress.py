"""Progress bars that stay readable in a log file.

tqdm redraws a bar ten times a second; redirected to a file, every redraw is kept and a long job's log swells to
megabytes. :func:`progress_bar` is ``tqdm.auto.tqdm`` (a widget in a notebook) with one change: a text bar whose stream
is not a terminal refreshes every ``LOG_MININTERVAL_S`` seconds (an explicit ``mininterval`` still wins).
"""

from __future__ import annotations

import sys
from typing import Any

from tqdm.auto import tqdm

LOG_MININTERVAL_S = 30.0
NOTEBOOK = any(c.__module__ == "tqdm.notebook" for c in tqdm.__mro__)  # tqdm.auto chose the widget


def progress_bar(*args: Any, **kwargs: Any) -> tqdm:
    stream = kwargs.get("file") or sys.stderr
    if not NOTEBOOK and not getattr(stream, "isatty", lambda: False)():
        kwargs.setdefault("mininterval", LOG_MININTERVAL_S)
    return tqdm(*args, **kwargs)
