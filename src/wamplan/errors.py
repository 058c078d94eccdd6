"""Errors meant for people: the CLI prints them as one line (no traceback) and exits with code 2."""

from __future__ import annotations

from pathlib import Path
from typing import Iterable


class UserError(Exception):
    """Bad input or a missing prerequisite; the message names the problem and the fix."""


def require_paths(paths: Iterable[str], flag: str, fix: str) -> None:
    """One line for the first of ``paths`` that is empty or does not exist: "FLAG PATH does not exist; FIX"."""
    for path in paths:
        if not path or not Path(path).exists():
            raise UserError(f"{flag} {path or '(empty)'} does not exist; {fix}")
