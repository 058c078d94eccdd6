"""Per-episode evaluation records: one JSON line each in ``DIR/records.jsonl``, appended and fsync-ed
as episodes finish, so a killed evaluation loses only episodes in flight and a re-run skips the rest."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

RECORDS = "records.jsonl"
CONFIG = "eval_config.json"  # the settings every record of a directory shares (runner: settings), written at start


def no_records(out_dir: str | Path) -> str:
    """The one line for an evaluation directory ``out_dir`` without a finished episode: one started (its settings
    stored) whose first episode has not finished, or not an evaluation directory at all (errors.not_a)."""
    from wamplan.errors import not_a

    out = Path(out_dir)
    if (out / CONFIG).is_file():
        return f"{out} holds an evaluation whose first episode has not finished; run or resume `wamplan eval --out {out}`"
    return not_a(out, RECORDS, "an evaluation directory", f"wamplan eval --out {out}")


def read_settings(out_dir: str | Path) -> dict[str, Any] | None:
    """The settings an evaluation directory stored (``eval_config.json``), or None where it stores none; one line
    naming the file if it is damaged (not JSON, or not a JSON object)."""
    from wamplan.errors import UserError, reason

    path = Path(out_dir) / CONFIG
    if not path.is_file():
        return None
    try:
        stored = json.loads(path.read_bytes())
    except (OSError, ValueError) as e:  # not readable, not UTF-8, not JSON
        raise UserError(f"{path} is damaged ({reason(e)}); restore it, or evaluate into a new --out (its records "
                        f"were made with the settings it held)") from None
    if not isinstance(stored, dict):
        raise UserError(f"{path} is damaged (a JSON {type(stored).__name__}, not the object of settings `wamplan "
                        f"eval` writes); restore it, or evaluate into a new --out")
    return stored


def record_key(rec: dict[str, Any]) -> tuple[int, int, str]:
    """(condition, seed, variant): what makes an episode's record unique in one output folder."""
    return int(rec["condition"]), int(rec["seed"]), str(rec.get("variant", "default"))


def read_records(out_dir: str | Path, repair: bool = False) -> list[dict[str, Any]]:
    """All complete records. A torn last line (a kill mid-write) is skipped, and cut off with ``repair``."""
    from wamplan.errors import UserError

    path = Path(out_dir) / RECORDS
    if not path.is_file():
        return []
    raw = path.read_bytes()
    head, _, tail = raw.rpartition(b"\n")
    good, torn = [], False
    lines = head.split(b"\n") if head else []
    for n, line in enumerate(lines + [tail], 1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except ValueError:  # not JSON, or not UTF-8
            torn = n == len(lines) + 1  # the last line, cut by a kill mid-write: dropped (cut off with ``repair``)
            if torn:
                break
            rec = None
        try:
            good.append(_checked(rec))
        except ValueError:
            raise UserError(f"{path} line {n} is damaged or not an episode record (a JSON object with integer "
                            f"'condition' and 'seed'); fix or delete that line and re-run to resume") from None
    if tail.strip():
        fix = None if torn else b"\n"  # a complete last record lacks only its newline
        if repair:
            with open(path, "r+b") as f:
                if fix is None:
                    f.truncate(len(raw) - len(tail))
                else:
                    f.seek(0, os.SEEK_END)
                    f.write(fix)
    return good


def _checked(rec: Any) -> dict[str, Any]:
    """``rec`` if it is a dict whose key fields ``record_key`` can read; ValueError otherwise.
    (JSONDecodeError is a ValueError, so one ``except ValueError`` covers both.)"""
    if not isinstance(rec, dict):
        raise ValueError("not a JSON object")
    if not all(isinstance(rec.get(k), int) and not isinstance(rec.get(k), bool) for k in ("condition", "seed")):
        raise ValueError("no integer condition and seed")
    return rec


def append_record(out_dir: str | Path, rec: dict[str, Any]) -> None:
    path = Path(out_dir) / RECORDS
    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps(rec) + "\n")
        f.flush()
        os.fsync(f.fileno())
