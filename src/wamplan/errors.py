"""Errors meant for people: the CLI prints them as one line (no traceback) and exits with code 2."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterable


class UserError(Exception):
    """Bad input or a missing prerequisite; the message names the problem and the fix."""


class TaskMismatch(UserError, ValueError):
    """Two things made for different tasks (an env and a policy, a WAM and a world model, a store and a run)."""


def require_paths(paths: Iterable[str], flag: str, fix: str) -> None:
    """One line for the first of ``paths`` that is empty or does not exist: "FLAG PATH does not exist; FIX"."""
    for path in paths:
        if not path or not Path(path).exists():
            raise UserError(f"{flag} {path or '(empty)'} does not exist; {fix}")


def checkpoint_kind(path: str | Path) -> str:
    """The ``kind`` a checkpoint directory's ``config.json`` (``checkpoint.CONFIG_FILE``) names, or "" where there is
    none or it cannot be read (for messages only: loading checks a checkpoint properly)."""
    import json

    try:
        kind = json.loads((Path(path) / "config.json").read_text()).get("kind", "")
    except (OSError, ValueError, AttributeError):
        return ""
    return kind if isinstance(kind, str) else ""


def not_a(path: str | Path, marker: str, what: str, make: str, also: tuple[str, ...] = ()) -> str:
    """The one line for ``path`` that should be ``what`` (a directory holding ``marker``) and is not: it does not
    exist, is a file, holds something else (``config.json``'s kind named where it is a checkpoint), or is an empty
    directory, where ``make`` (a command that fills it) is the fix; ``also``: other commands that make one."""
    p = Path(path)
    use = f"pass {what} (made by {' or '.join(f'`{c}`' for c in (make.split(' --out')[0], *also))})"
    if not p.exists():
        return f"{p} does not exist; {use}"
    if not p.is_dir():
        return f"{p} is a file, not {what}; {use}"
    if not any(e.name != ".lock" for e in p.iterdir()):  # a run's write lock alone (wamplan.locks) holds nothing
        return f"{p} is empty; run `{make}` first"
    kind = checkpoint_kind(p)
    holds = f"a '{kind}' checkpoint" if kind else f"no {marker}"
    return f"{p} is not {what} (it holds {holds}); {use}"


SEED_LIMIT = 2**32  # episode seeds seed NumPy and ManiSkill, which take 32-bit unsigned seeds


def require_seeds(first: int, count: int = 1, flag: str = "--seed-start", count_flag: str = "--episodes") -> None:
    """One line unless the episode seeds ``first .. first + count - 1`` all lie in [0, 2**32): a first seed outside
    blames ``flag``, a count that runs past the last seed ``count_flag``."""
    last = f" .. {first + count - 1}" if count > 1 else ""
    if first < 0 or first >= SEED_LIMIT:
        raise UserError(f"{flag} {first}: episode seeds must lie in 0 .. {SEED_LIMIT - 1} (got {first}{last}); "
                        f"pass a seed in that range")
    if first + max(count, 1) - 1 >= SEED_LIMIT:
        most = SEED_LIMIT - first
        raise UserError(f"{count_flag} {count}: the seeds {first} .. {first + count - 1} (from {flag} {first}) run "
                        f"past the last one, and episode seeds must lie in 0 .. {SEED_LIMIT - 1}; pass at most "
                        f"{most} episode{'s' * (most > 1)} from there")


def require_distinct(paths: Iterable[str | Path], flag: str, what: str) -> None:
    """One line if two of ``paths`` are one file or directory (however spelled): it would be read twice."""
    seen: dict[Path, str] = {}
    for path in map(str, paths):
        key = Path(path).resolve()
        if key in seen:
            same = f"{path} twice" if seen[key] == path else f"{seen[key]} and {path}, one {what}"
            raise UserError(f"{flag} names {same}; name each {what} once")
        seen[key] = path


def require_positive(*given: tuple[str, Any]) -> None:
    """One line for the first ``(flag, value)`` of ``given`` whose value is below 1 (None: not given), naming that
    flag and the value typed: "--workers 0 must be at least 1"."""
    for flag, value in given:
        if value is not None and value < 1:
            raise UserError(f"{flag} {value} must be at least 1")


def require_dir(path: str | Path, flag: str = "--out") -> Path:
    """``path`` as a directory to write into (created later if missing); one line, before any work, if it is an
    existing file or cannot be written (:func:`require_writable`)."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise UserError(f"{flag} {p} is a file, not a directory; pass a directory (a new one is created)")
    require_writable(p, flag)
    return p


def require_own_dir(path: str | Path, marks: Iterable[str], what: str, flag: str = "--out") -> None:
    """One line if ``path`` is a non-empty directory holding none of ``marks`` (the names that mark it as
    ``what``): writing there would mix ``what`` into something else (an episode store, a training run). A run's
    write lock (``.lock``) alone does not count."""
    p, marks = Path(path), tuple(marks)
    if p.is_dir() and any(e.name != ".lock" for e in p.iterdir()) and not any((p / m).exists() for m in marks):
        raise UserError(f"{flag} {p} exists and is not {what} (no {' or '.join(marks)} inside, it would be mixed "
                        f"up); pass a new or empty directory")


def require_writable(path: str | Path, flag: str = "--out", fix: str = "pass a directory you can write to (or make "
                     "it writable)", shown: str | Path | None = None) -> None:
    """One line unless files can be created in the directory ``path``, or, where it does not exist yet, in its
    nearest existing parent (where it will be created): a file in the way, a read-only filesystem or missing
    permissions. The check creates (and at once removes) a nameless file there, so it sees what the filesystem
    allows, whoever runs it. Every writer runs it (directly, or through :func:`require_dir` and
    :func:`require_file`) before its work starts; ``shown``: the path the line names (default ``path``)."""
    p = Path(path)
    shown = p if shown is None else shown
    probe = p.absolute()
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        raise UserError(f"{flag} {shown}: {probe} is a file, so no directory can be made under it; pass a path whose "
                        f"parents are directories")
    try:
        with tempfile.TemporaryFile(dir=probe):
            pass
    except OSError as e:
        raise UserError(f"{flag} {shown} cannot be written ({e.strerror or reason(e)} in {probe}); {fix}") from None


def require_file(path: str | Path | None, flag: str) -> Path | None:
    """``path`` as a file to write (None: not asked for); one line, before any work, if it is a directory, its
    folder is a file, or it cannot be written there (:func:`require_writable`; a missing folder is the writer's to
    create)."""
    if path is None:
        return None
    p = Path(path)
    if p.is_dir():
        raise UserError(f"{flag} {p} is a directory, not a file; pass a file name")
    if any(q.is_file() for q in p.parents):
        raise UserError(f"{flag} {p}: {next(q for q in p.parents if q.is_file())} is a file, not a folder; pass a "
                        f"path in a folder")
    fix = "pass a file in a folder you can write to (or make it writable)"
    require_writable(p.parent, flag, fix, shown=p)
    if p.is_file() and not os.access(p, os.W_OK):
        raise UserError(f"{flag} {p} cannot be written (the file is read-only); {fix}")
    return p


def reason(e: BaseException) -> str:
    """``TypeName: the first line of its message``: a library's exception, quoted inside one line for people."""
    text = str(e).strip()
    return f"{type(e).__name__}: {text.splitlines()[0]}" if text else type(e).__name__


def run_script(main: Callable[[], Any], name: str) -> None:
    """Run a repository script's ``main()``; bad input (a :class:`UserError`) is one line on stderr, ``NAME: error:
    ...``, with exit status 2 and no traceback."""
    import sys

    try:
        main()
    except UserError as e:
        print(f"{name}: error: {e}", file=sys.stderr)
        sys.exit(2)
