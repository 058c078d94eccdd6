"""Every writer checks, before its work, that it can write where it will (one shared check,
``wamplan.errors.require_writable``), and a damaged input file is one line naming it (issue 75, items 1-2).

A read-only place is made by the check's own probe: creating a file in a marked directory raises EROFS, as on a
read-only mount (root, who runs these tests here, ignores a directory's mode). The directory itself stays writable,
so a writer that skipped the check would write there and exit 0: each case asserts exit 2 and nothing written."""

from __future__ import annotations

import errno
import json
import os
import tempfile
from pathlib import Path

import pytest

from test_errors import refused as one_line  # run a command: exit 2, one error line naming each given part
from wamplan.cli import main

MINI = Path(__file__).resolve().parents[1] / "checkpoints" / "mini"


@pytest.fixture
def read_only(monkeypatch):
    """``read_only(path)``: from now on no file can be created in the directory ``path`` (EROFS)."""
    marked: set[Path] = set()
    real = tempfile.TemporaryFile

    def probe(*args, dir=None, **kwargs):
        if dir is not None and Path(dir).resolve() in marked:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS))
        return real(*args, dir=dir, **kwargs)

    monkeypatch.setattr(tempfile, "TemporaryFile", probe)

    def mark(path: Path) -> Path:
        path.mkdir(parents=True, exist_ok=True)
        marked.add(path.resolve())
        return path

    return mark


def _metrics(run: Path) -> Path:
    run.mkdir(parents=True, exist_ok=True)
    (run / "metrics.jsonl").write_text("".join(json.dumps(dict(event="epoch", epoch=e, global_step=10 * e,
                                                                **{"train/loss": 1.0 / e})) + "\n" for e in (1, 2)))
    return run


def _records(d: Path) -> Path:
    d.mkdir(parents=True, exist_ok=True)
    (d / "records.jsonl").write_text("".join(json.dumps(dict(condition=1, seed=s, variant="open-loop", success=True,
                                                             outcome="success", length=100)) + "\n" for s in (0, 1)))
    return d


@pytest.mark.parametrize("case", ["env render", "env rollout --json", "data view", "plot --out", "plot (default)",
                                  "report"])
def test_a_writer_checks_its_place_before_it_works(tmp_path, capsys, read_only, case):
    ro = tmp_path / "ro"
    argv, target = {
        "env render": (["env", "render", "--seed", "0", "--camera-size", "64", "--out", ro / "views.png"],
                       ro / "views.png"),
        "env rollout --json": (["env", "rollout", "--policy", "expert", "--episodes", "1", "--camera-size", "64",
                                "--json", ro / "r.json"], ro / "r.json"),
        "data view": (["data", "view", tmp_path / "no_store", "--out", ro / "sheet.png"], ro / "sheet.png"),
        "plot --out": (["plot", _metrics(tmp_path / "run"), "--out", ro / "c.png"], ro / "c.png"),
        "plot (default)": (["plot", _metrics(ro)], ro / "curves.png"),
        "report": (["report", _records(ro)], ro),
    }[case]
    before = sorted(p.name for p in ro.iterdir()) if ro.is_dir() else []
    read_only(ro)
    line = one_line(capsys, argv, target, "cannot be written", "Read-only file system")
    assert ("wamplan report NEW" in line) == (case == "report")  # the report's fix: a new directory
    assert sorted(p.name for p in ro.iterdir()) == before  # nothing written


def test_damaged_inputs_are_one_line_naming_the_file(tmp_path, capsys):
    from wamplan.data.store import SCHEMA_VERSION

    store = tmp_path / "store"
    store.mkdir()
    manifest = dict(format="wamplan-episode-store", schema_version=SCHEMA_VERSION, image_every="four",
                    env={"task": "cube-insertion"}, cameras=["front"])
    (store / "store.json").write_text(json.dumps(manifest))
    one_line(capsys, ["data", "info", store], store / "store.json", "is damaged", "image_every 'four'")
    (store / "store.json").write_text(json.dumps(dict(manifest, image_every=4, env=[1])))
    one_line(capsys, ["data", "info", store], store / "store.json", "is damaged", "env [1]")

    text = tmp_path / "notes.txt"
    text.write_text("hello\nworld\n")
    one_line(capsys, ["plot", text, "--out", tmp_path / "c.png"], text, "line 1 is not a training metrics record")
    assert not (tmp_path / "c.png").exists()
    run = _metrics(tmp_path / "run")
    with open(run / "metrics.jsonl", "a") as f:
        f.write('{"event": "epoch", "epo')  # a kill mid-write: the torn last line is left out, the rest drawn
    assert main(["plot", str(run)]) == 0 and (run / "curves.png").is_file()

    ev = _records(tmp_path / "eval")
    (ev / "eval_config.json").write_text("{not json")
    one_line(capsys, ["eval", "--conditions", "1", "--episodes", "1", "--wam", MINI / "tinywam", "--out", ev],
             ev / "eval_config.json", "is damaged")
    one_line(capsys, ["report", ev], ev / "eval_config.json", "is damaged")
    assert (ev / "eval_config.json").read_text() == "{not json" and not (ev / "table1.md").exists()
    (ev / "eval_config.json").write_text("[1, 2]")
    one_line(capsys, ["report", ev], ev / "eval_config.json", "a JSON list")


# ------------------------------------------------------------------------------ one writer an output directory
def test_eval_holds_its_directory_until_the_last_record(tmp_path, capsys):
    import subprocess
    import sys

    from wamplan.cli.eval_options import eval_config_from_args  # noqa: F401 (the parser's config, as eval builds it)
    from wamplan.evaluation.config import EvalConfig
    from wamplan.evaluation.runner import run_evaluation
    from wamplan.locks import dir_lock

    ev = _records(tmp_path / "eval")  # seeds 0 and 1 of condition 1 recorded: nothing left to run
    records = (ev / "records.jsonl").read_text()
    argv = ["eval", "--conditions", "1", "--episodes", "2", "--wam", MINI / "tinywam", "--out", ev]
    with dir_lock(ev, "evaluated into"):  # as another `wamplan eval` into it would hold it
        one_line(capsys, argv, ev, "is being evaluated into by another process now", "another --out")
    assert (ev / "records.jsonl").read_text() == records and not (ev / "eval_config.json").exists()
    assert main([str(a) for a in argv]) == 0  # free again
    capsys.readouterr()
    # a run killed while it held the directory leaves no stale lock behind
    held = f"import os; from wamplan.locks import dir_lock\nwith dir_lock({str(ev)!r}): os.kill(os.getpid(), 9)"
    assert subprocess.run([sys.executable, "-c", held]).returncode == -9
    assert main([str(a) for a in argv]) == 0
    capsys.readouterr()
    # held from the call (the checks) until its records are all written, in the process that writes them
    gen = run_evaluation(EvalConfig(wam=str(MINI / "tinywam")), [1], [0, 1], ev)
    with pytest.raises(Exception, match="is being evaluated into"), dir_lock(ev, "evaluated into"):
        pass
    assert list(gen) == []
    with dir_lock(ev, "evaluated into"):
        pass


def test_collect_holds_its_store(tmp_path, capsys):
    from wamplan.data.store import EpisodeStore
    from wamplan.envs.config import EnvConfig
    from wamplan.locks import LOCK_FILE, dir_lock

    env = EnvConfig(camera_size=64)
    store = EpisodeStore(tmp_path / "store", create=True, env=env.task_kwargs(), image_every=4, task=env.spec).root
    with dir_lock(store, "collected into"):  # as another `wamplan collect` into it would hold it
        one_line(capsys, ["collect", "--source", "expert", "--episodes", "1", "--camera-size", "64", "--out", store],
                 store, "is being collected into by another process now")
    assert sorted(p.name for p in (store / "episodes").iterdir()) == []
    # a directory holding only a lock a finished collector left is still new: a store is made in it
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    (fresh / LOCK_FILE).touch()
    EpisodeStore(fresh, create=True, env=env.task_kwargs(), image_every=4, task=env.spec)
    assert (fresh / "store.json").is_file()


def test_report_counts_a_seed_once(tmp_path, capsys):
    from wamplan.evaluation.report import merged_records, table1

    ev = _records(tmp_path / "eval")
    first = (ev / "records.jsonl").read_text()
    rec = json.loads(first.splitlines()[0])
    with open(ev / "records.jsonl", "a") as f:  # the same episodes, recorded again by a second run at once
        f.write(first.replace('"length": 100', '"length": 100, "wall_time_s": 9.5'))
    rows = table1(merged_records([ev]))
    assert [(r["episodes"], r["successes"]) for r in rows] == [(2, 2)]
    assert main(["report", str(ev)]) == 0 and "| 2 | 100% " in (ev / "table1.md").read_text()
    capsys.readouterr()
    with open(ev / "records.jsonl", "a") as f:  # seed 0 once more with another outcome, seed 7 twice, apart
        for s, success, length in ((0, False, 300), (7, True, 120), (7, True, 140)):
            f.write(json.dumps(dict(rec, seed=s, success=success, outcome="success" if success else "never_lifted",
                                    length=length)) + "\n")
    one_line(capsys, ["report", ev], "condition 1 (open-loop) seeds 0, 7", "recorded twice with different outcomes")
