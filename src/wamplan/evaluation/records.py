"""Per-episode evaluation records: one JSON line each in ``DIR/records.jsonl``, appended and fsync-ed
as episodes finish, so a killed evaluation loses only episodes in flight and a re-run skips the rest."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

RECORDS = "records.jsonl"


def record_key(rec: dict[str, Any]) -> tuple[int, int, str]:
    return int(rec["condition"]), int(rec["seed"]), str(rec.get("variant", "default"))


def read_records(out_dir: str | Path, repair: bool = False) -> list[dict[str, Any]]:
    """All complete records. A torn last line (a kill mid-write) is skipped, and cut off with ``repair``."""
    from wamplan.errors import UserError

    path = Path(out_dir) / RECORDS
    if not path.is_file():
        return []
    raw = path.read_bytes()
    head, _, tail = raw.rpartition(b"\n")
    good = []
    for n, line in enumerate(head.split(b"\n") if head else [], 1):
        if line.strip():
            try:
                good.append(json.loads(line))
            except json.JSONDecodeError:
                raise UserError(f"{path} line {n} is damaged; fix or delete that line and re-run to resume") from None
    if tail.strip():
        try:
            good.append(json.loads(tail))  # complete record whose newline was never written
            fix = b"\n"
        except json.JSONDecodeError:
            fix = None  # torn: drop it
        if repair:
            with open(path, "r+b") as f:
                if fix is None:
                    f.truncate(len(raw) - len(tail))
                else:
                    f.seek(0, os.SEEK_END)
                    f.write(fix)
    return good


def append_record(out_dir: str | Path, rec: dict[str, Any]) -> None:
    path = Path(out_dir) / RECORDS
    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps(rec) + "\n")
        f.flush()
        os.fsync(f.fileno())
