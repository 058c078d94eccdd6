"""Help a newcomer can read (issue 75 item 6): a long command's ``--help`` shows the options most runs need and names
the groups the rest sit in, ``--help-all`` lists every option; and the parsers build without torch, ManiSkill or
transformers (so an uncached ``--help`` does not wait on them)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from wamplan.cli.main import main

SRC = Path(__file__).resolve().parents[1] / "src"

# command -> (options on its first screen, options only --help-all lists)
SCREENS = {
    "eval": (("--out", "--wam", "--wm-augmented", "--conditions", "--episodes", "--planner", "--task"),
             ("--first-chunk", "--render-backend", "--cost-name", "--num-candidates", "--wam-profile")),
    "serve": (("--upstream", "--world-model", "--profile", "--port", "--secret", "--budget-ms"),
              ("--ws-fields", "--max-sessions", "--cost-name", "--temperature", "--first-chunk")),
    "collect": (("--source", "--episodes", "--out", "--task", "--workers"),
                ("--branch-sigmas", "--expert-gain", "--noisy-noise-std", "--render-backend")),
    "wm train": (("--data", "--out", "--preset", "--epochs", "--init", "--device"),
                 ("--betas", "--depth", "--sibling-weight", "--encoder-path")),
    "wam train": (("--data", "--out", "--epochs", "--lr", "--device"),
                  ("--image-weight", "--channels", "--shift-pixels", "--precision")),
}


def _help(capsys, args: list[str]) -> str:
    with pytest.raises(SystemExit) as e:
        main(args)
    assert e.value.code == 0
    return capsys.readouterr().out


@pytest.mark.parametrize("command", sorted(SCREENS))
def test_help_shows_the_first_screen_and_help_all_the_rest(command, capsys, monkeypatch, tmp_path):
    monkeypatch.setenv("WAMPLAN_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("COLUMNS", "100")
    first, rest = SCREENS[command]
    for _ in range(2):  # built, then read from the help cache
        brief = _help(capsys, [*command.split(), "--help"])
        full = _help(capsys, [*command.split(), "--help-all"])
        assert all(f in brief for f in first) and not [f for f in rest if f in brief]
        said = " ".join(brief.split()).replace("- ", "-")  # argparse wraps the text to the terminal, at hyphens too
        assert f"`wamplan {command} --help-all` lists them all" in said and "More options, in groups:" in said
        assert all(f in full for f in (*first, *rest))
        assert len(brief.splitlines()) <= 50 < len(full.splitlines())


def test_building_every_parser_imports_no_torch_maniskill_or_transformers():
    """Each command's options are built (as for its ``--help``) in a fresh interpreter; none of the heavy libraries
    is imported."""
    code = """
import sys
import argparse
from wamplan.cli.main import build_parser
heavy = ("torch", "mani_skill", "sapien", "transformers")

def walk(parser):
    loaded = [m for m in heavy if m in sys.modules]
    if loaded:
        sys.exit(f"{parser.prog}: {loaded}")
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name in list(action.choices):
                walk(action.build(name))

walk(build_parser())
print("ok")
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          env={"PYTHONPATH": str(SRC), "PATH": "/usr/bin:/bin", "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr[-2000:]
