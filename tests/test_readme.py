"""The guide cannot rot: every ```python block of README.md and docs/*.md runs as written, each in a fresh
Python process from the repository root (as after `make demo`'s set-up: the shipped checkpoints in place).
A fragment that is not meant to run on its own is fenced another way (```text, or ```py for highlighting).

A ```python block followed directly (blank lines only between) by a ```text block must print that text: line
for line, every token exactly except decimal numbers (a '.' and digits), which may differ by a relative
FLOAT_RTOL (or by one unit in the last shown digit), since the same checkpoints give slightly different numbers
on another machine. Show only what holds on every machine: an episode's outcome for a seed does not (seed 0 of
the README's example succeeded at step 165 on the machine that wrote it and fails at step 300 on others).

A block that calls ``run_episode`` runs with its episodes cut at EPISODE_STEPS (``run_episode``'s own ``max_steps``
option, which ``CAP_EPISODES`` sets as the default before the block runs; a block that passes ``max_steps`` keeps
its own): the text stays what a user runs, every call in it still runs and prints what is shown, and the test does
not plan a 300-step episode (which outcome it reaches is not shown, see above). EPISODE_STEPS = 48 is the paper's
open-loop first chunk and two planned ones."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FENCE = re.compile(r"^```python[ \t]*\n(.*?)^```[ \t]*$", re.MULTILINE | re.DOTALL)
SHOWN = re.compile(r"\n(?:[ \t]*\n)*```text[ \t]*\n(.*?)^```[ \t]*$", re.MULTILINE | re.DOTALL)  # right after a block
DECIMAL = re.compile(r"(?<![\w.])([-+]?\d+\.\d+(?:[eE][-+]?\d+)?)(?![\w.])")
FLOAT_RTOL = 0.10
EPISODE_STEPS = 48
CAP_EPISODES = ("import wamplan as _wamplan, wamplan.api as _api\n"
                "def _capped(env, policy, seed, _run=_api.run_episode, **options):\n"
                f"    return _run(env, policy, seed, **{{'max_steps': {EPISODE_STEPS}, **options}})\n"
                "_wamplan.run_episode = _api.run_episode = _capped\n"
                "del _wamplan, _api, _capped\n")


def python_blocks(path: Path) -> list[tuple[int, str]]:
    """(line number, code) of every block fenced ```python in ``path``."""
    return [(line, code) for line, code, _ in blocks_with_output(path)]


def blocks_with_output(path: Path) -> list[tuple[int, str, str | None]]:
    """(line number, code, shown output) of every ```python block in ``path``; the output is the ```text block
    that directly follows it (blank lines only between), else None."""
    text = path.read_text()
    found = []
    for m in FENCE.finditer(text):
        shown = SHOWN.match(text, m.end())
        found.append((text.count("\n", 0, m.start()) + 1, m.group(1), shown.group(1) if shown else None))
    return found


def output_mismatch(shown: str, printed: str) -> str | None:
    """Why ``printed`` is not the ``shown`` output, or None when it is: the same lines (trailing blanks ignored),
    decimal numbers within FLOAT_RTOL relative (or one unit in the shown last digit), every other character
    exactly."""
    want, got = shown.rstrip("\n").splitlines(), printed.rstrip("\n").splitlines()
    if len(want) != len(got):
        return f"{len(got)} lines printed, {len(want)} shown"
    for i, (w, g) in enumerate(zip(want, got), 1):
        w_parts, g_parts = DECIMAL.split(w.rstrip()), DECIMAL.split(g.rstrip())
        if len(w_parts) != len(g_parts) or w_parts[::2] != g_parts[::2]:
            return f"line {i}: printed {g!r}, shown {w!r}"
        for a, b in zip(w_parts[1::2], g_parts[1::2]):
            digits = len(a.lower().split("e")[0].split(".")[1])
            unit = 10.0 ** (int(a.lower().split("e")[1]) if "e" in a.lower() else 0) * 10.0 ** -digits
            if abs(float(b) - float(a)) > max(FLOAT_RTOL * abs(float(a)), unit):
                return f"line {i}: {b} printed, {a} shown (more than {FLOAT_RTOL:.0%} apart): {g!r}"
    return None


def _documents() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


BLOCKS = [(p, line, code, shown) for p in _documents() for line, code, shown in blocks_with_output(p)]


def test_blocks_are_found(tmp_path):
    assert any("wamplan.planned_policy" in code for _, code in python_blocks(ROOT / "README.md")), \
        "README.md has no ```python block with the API example"
    probe = tmp_path / "probe.md"
    probe.write_text("intro\n```python\nprint(1)\n```\n```text\nnot python\n```\n```python\nx = 2\n```\n")
    assert python_blocks(probe) == [(2, "print(1)\n"), (8, "x = 2\n")]
    assert blocks_with_output(probe) == [(2, "print(1)\n", "not python\n"), (8, "x = 2\n", None)]
    probe.write_text("```python\na = 1\n```\nprose between\n```text\n1\n```\n")
    assert blocks_with_output(probe) == [(1, "a = 1\n", None)]


def test_readme_example_shows_its_output():
    shown = [(line, out) for line, code, out in blocks_with_output(ROOT / "README.md")
             if "wamplan.planned_policy" in code]
    assert shown and all(out for _, out in shown), \
        f"the README's API example (line {shown[0][0] if shown else '?'}) should be followed by its ```text output"


@pytest.mark.parametrize("shown, printed", [
    ("None (16, 5) cost 0.0608 -> 0.0554\nTrue x\n", "None (16, 5) cost 0.0608 -> 0.0554\nTrue x\n"),
    ("None (16, 5) cost 0.0608 -> 0.0554\n", "None (16, 5) cost 0.0650 -> 0.0510\n\n"),  # within 10 %
    ("loss 0.0\n", "loss 0.04\n"),  # one unit of the shown last digit
    ("x 1.5e-03\n", "x 1.6e-03\n"),
])
def test_output_matches(shown, printed):
    assert output_mismatch(shown, printed) is None


@pytest.mark.parametrize("shown, printed, why", [
    ("True success 165\n", "False descended_not_seated 300\n", "line 1"),
    ("steps 165\n", "steps 166\n", "line 1"),  # integers are exact
    ("cost 0.0608 -> 0.0554\n", "cost 0.0608 -> 0.0480\n", "more than 10%"),
    ("(16, 5)\n", "(16, 5)\nextra\n", "2 lines printed, 1 shown"),
    ("cost 0.0608\n", "cost nan\n", "line 1"),
])
def test_output_mismatches(shown, printed, why):
    assert why in (output_mismatch(shown, printed) or "")


@pytest.mark.parametrize("path, line, code, shown", BLOCKS,
                         ids=[f"{p.relative_to(ROOT)}:{line}" for p, line, _, _ in BLOCKS])
def test_python_block_runs(path: Path, line: int, code: str, shown: str | None):
    env = dict(os.environ, OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "1"))
    prelude = CAP_EPISODES if "run_episode(" in code else ""  # (its lines come first in a traceback's numbers)
    run = subprocess.run([sys.executable, "-c", prelude + code], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=600)
    where = path.relative_to(ROOT)
    assert run.returncode == 0, (f"the ```python block at {where}:{line} failed:\n{prelude}{code}\n"
                                 f"--- stderr ---\n{run.stderr[-3000:]}")
    if shown is not None:
        why = output_mismatch(shown, run.stdout)
        assert why is None, (f"the ```python block at {where}:{line} does not print the ```text block after it "
                             f"({why}):\n--- printed ---\n{run.stdout}--- shown ---\n{shown}")


def test_a_block_that_runs_an_episode_stops_at_the_cap_and_keeps_its_own_max_steps(monkeypatch):
    """CAP_EPISODES cuts ``wamplan.run_episode`` (and ``wamplan.api.run_episode``) at EPISODE_STEPS unless the block
    gives ``max_steps``; the env, policy, seed and other options reach the real function unchanged."""
    import wamplan
    from wamplan import api

    seen = []
    monkeypatch.setattr(api, "_run_episode", lambda env, policy, seed, **options: seen.append((seed, options)))
    monkeypatch.setattr(api, "run_episode", api.run_episode)  # both put back after the test
    monkeypatch.setattr(wamplan, "run_episode", api.run_episode, raising=False)
    exec(CAP_EPISODES, {})
    wamplan.run_episode("env", "policy", 3)
    api.run_episode("env", "policy", 4, max_steps=7, stop_on_success=False)
    assert seen == [(3, {"max_steps": EPISODE_STEPS}), (4, {"max_steps": 7, "stop_on_success": False})]


def test_the_task_list_shown_is_what_wamplan_tasks_prints(capsys):
    from wamplan.cli import main

    text = (ROOT / "README.md").read_text()
    shown = re.search(r"`wamplan tasks` lists the registered ones:\n\n```\n(.*?)```", text, re.DOTALL)
    assert shown, "README.md should show `wamplan tasks`' output after 'lists the registered ones:'"
    assert main(["tasks"]) == 0
    printed = capsys.readouterr().out
    assert printed.split() == shown.group(1).split(), f"printed:\n{printed}\nshown:\n{shown.group(1)}"
