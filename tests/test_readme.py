"""The guide cannot rot: every ```python block of README.md and docs/*.md runs as written, each in a fresh
Python process from the repository root (as after `make demo`'s set-up: the shipped checkpoints in place).
A fragment that is not meant to run on its own is fenced another way (```text, or ```py for highlighting)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FENCE = re.compile(r"^```python[ \t]*\n(.*?)^```[ \t]*$", re.MULTILINE | re.DOTALL)


def python_blocks(path: Path) -> list[tuple[int, str]]:
    """(line number, code) of every block fenced ```python in ``path``."""
    text = path.read_text()
    return [(text.count("\n", 0, m.start()) + 1, m.group(1)) for m in FENCE.finditer(text)]


def _documents() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


BLOCKS = [(p, line, code) for p in _documents() for line, code in python_blocks(p)]


def test_blocks_are_found(tmp_path):
    assert any("wamplan.planned_policy" in code for _, code in python_blocks(ROOT / "README.md")), \
        "README.md has no ```python block with the API example"
    probe = tmp_path / "probe.md"
    probe.write_text("intro\n```python\nprint(1)\n```\n```text\nnot python\n```\n```python\nx = 2\n```\n")
    assert python_blocks(probe) == [(2, "print(1)\n"), (8, "x = 2\n")]


@pytest.mark.parametrize("path, line, code", BLOCKS,
                         ids=[f"{p.relative_to(ROOT)}:{line}" for p, line, _ in BLOCKS])
def test_python_block_runs(path: Path, line: int, code: str):
    env = dict(os.environ, OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "1"))
    run = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, (f"the ```python block at {path.relative_to(ROOT)}:{line} failed:\n{code}\n"
                                 f"--- stderr ---\n{run.stderr[-3000:]}")
