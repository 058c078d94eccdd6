"""Task plug-ins: a distribution that names a module in the entry-point group ``wamplan.tasks`` adds its tasks to
``wamplan tasks``, to every ``--task`` (and its help) and to the spawned collection workers.

Each plug-in here is a path-based distribution (a ``NAME.dist-info`` with ``entry_points.txt`` beside its module,
in a directory put on ``PYTHONPATH``), used by ``wamplan`` in a subprocess, as after ``pip install``."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import h5py
import pytest

import wamplan

SRC = Path(wamplan.__file__).resolve().parents[1]

MY_TASK = '''
from wamplan.envs.maniskill import maniskill_task
from wamplan.envs.spec import register_task

register_task(maniskill_task("PushCube-v1", name="my-task", cameras=("base_camera",), action_dim=7, proprio_dim=16,
                             max_episode_steps=50, instruction="push the cube to the goal region"))
'''


def _plugin(site: Path, dist: str, module: str, code: str) -> Path:
    """Install ``module`` (``code``) as the distribution ``dist`` whose one task plug-in it is, into ``site``."""
    site.mkdir(parents=True, exist_ok=True)
    (site / f"{module}.py").write_text(code)
    info = site / f"{dist}-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[wamplan.tasks]\n{module} = {module}\n")
    return site


def _wamplan(*args: str, site: Path | None = None) -> subprocess.CompletedProcess:
    path = [str(SRC)] + ([str(site)] if site else [])
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(path), OMP_NUM_THREADS="1", COLUMNS="200")
    return subprocess.run([sys.executable, "-m", "wamplan.cli", *args], env=env, capture_output=True, text=True,
                          timeout=300)


def test_a_plugin_task_is_listed_and_collected_in_spawned_workers(tmp_path):
    site = _plugin(tmp_path / "site", "my-wamplan-tasks", "my_tasks", MY_TASK)
    before = _wamplan("collect", "--help")  # caches the help without the plug-in
    assert before.returncode == 0 and "my-task" not in before.stdout
    listed = _wamplan("tasks", site=site)
    assert listed.returncode == 0 and not listed.stderr, listed.stderr
    assert any(line.startswith("my-task ") and "env PushCube-v1" in line for line in listed.stdout.splitlines())
    helped = _wamplan("collect", "--help", site=site)  # the cache notices the new plug-in
    assert "--task {cube-insertion,my-task," in helped.stdout
    out = tmp_path / "store"
    done = _wamplan("collect", "--task", "my-task", "--source", "pink", "--episodes", "1", "--workers", "2",
                    "--max-steps", "3", "--camera-size", "16", "--out", str(out), site=site)  # one spawned worker
    assert done.returncode == 0, done.stderr
    files = sorted(out.glob("episodes/*.h5"))
    assert len(files) == 1
    with h5py.File(files[0]) as f:
        assert f["actions"].shape == (3, 7)


@pytest.mark.parametrize("code, problem", [
    ("import no_such_package\n", "failed to import (ModuleNotFoundError: No module named 'no_such_package')"),
    (MY_TASK.replace('name="my-task"', 'name="push-cube"'), "registers a name already taken (task 'push-cube'"),
])
def test_a_broken_plugin_is_left_out_with_one_line(tmp_path, code, problem):
    """A plug-in that fails to import or takes a registered name is left out whole: one line names its distribution
    and the problem; the other tasks still work, and asking for one of its tasks says why it is missing."""
    site = _plugin(tmp_path / "site", "my-wamplan-tasks", "my_tasks", MY_TASK.replace("my-task", "my-other") + code)
    listed = _wamplan("tasks", site=site)
    assert listed.returncode == 0 and "cube-insertion" in listed.stdout and "my-other" not in listed.stdout
    line, = listed.stderr.strip().splitlines()
    assert "'my-wamplan-tasks'" in line and problem in line and "my_tasks = my_tasks" in line
    asked = _wamplan("env", "check", "--task", "my-other", "--steps", "1", site=site)
    assert asked.returncode == 2
    assert "unknown task 'my-other'" in asked.stderr and problem in asked.stderr.splitlines()[-1]
