"""The Ray back-end (``--ray``) on a local 2-CPU cluster: evaluation records and collected episodes equal the
local runner's on the same seeds, a run cut short resumes without recording anything twice, an actor killed
mid-item is restarted and its item retried once, and without Ray ``--ray`` fails in one line."""

from __future__ import annotations

import itertools
import os
import subprocess
import sys

import numpy as np
import pytest

from wamplan.cli import main
from wamplan.evaluation.records import read_records, record_key
from wamplan.parallel import Backend, imap_workers

MINI = "checkpoints/mini/tinywam"
EVAL = ["eval", "--conditions", "1", "--episodes", "2", "--seed-start", "900", "--wam", MINI, "--max-steps", "16",
        "--camera-size", "64"]  # one chunk per episode: the records compared, not what an episode reaches
TIMING = {"wall_time_s", "finished", "chunk_timing_s", "created"}


@pytest.fixture(scope="module")
def ray_cluster():
    """One local Ray instance for the module (starting one costs seconds); the runs below join it."""
    ray = pytest.importorskip("ray")
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)  # not a running cluster
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the test workers below, not importable there
    yield ray
    ray.shutdown()


def untimed(x):
    """A record without its timing fields (wall clock, timestamps; per-chunk ``*_s``)."""
    if isinstance(x, dict):
        return {k: untimed(v) for k, v in x.items() if k not in TIMING and not k.endswith("_s")}
    return [untimed(v) for v in x] if isinstance(x, list) else x


def test_eval_on_ray_equals_local_and_resumes(ray_cluster, tmp_path, capsys):
    from wamplan.cli.eval_options import eval_config_from_args
    from wamplan.evaluation.runner import run_evaluation
    from wamplan.cli import build_parser

    # An episode does not depend on what its process ran before (the reset rebuilds the scene once physics has
    # stepped; tests/test_episode_independence.py): one local process (one thread, like a Ray actor) runs both seeds
    # as the reference, so seed 901 runs second there and first on its own actor below. On Ray the cut-short run's
    # one actor records seed 900 and the resumed run starts a fresh actor for seed 901.
    log = tmp_path / "local.log"
    with log.open("w") as f:
        code = subprocess.run([sys.executable, "-m", "wamplan.cli", *EVAL, "--out", str(tmp_path / "local")],
                              stdout=f, stderr=subprocess.STDOUT, env=dict(os.environ, OMP_NUM_THREADS="1")).returncode
    assert code == 0, log.read_text()[-3000:]
    local = {record_key(r): untimed(r) for r in read_records(tmp_path / "local")}
    assert sorted(local) == [(1, 900, "open-loop"), (1, 901, "open-loop")]

    # a driver that stops after its first record (seed 901, in flight on the actor by then, is lost, not
    # half-recorded)
    out = tmp_path / "ray"
    cfg = eval_config_from_args(build_parser().parse_args([*EVAL, "--out", str(out)]))
    run = run_evaluation(cfg, [1], [900, 901], out, workers=1, backend=Backend("ray"))
    first = list(itertools.islice(run, 1))
    run.close()
    assert len(first) == 1 and len(read_records(out)) == 1
    assert [record_key(r) for r in read_records(out)] == [(1, 900, "open-loop")]

    assert main([*EVAL, "--out", str(out), "--ray", "--workers", "2"]) == 0  # the re-run resumes
    assert "resuming: 1 of 2 episodes already recorded" in capsys.readouterr().out
    recs = read_records(out)
    assert len(recs) == 2 and {record_key(r): untimed(r) for r in recs} == local

    assert main([*EVAL, "--out", str(out), "--ray"]) == 0  # nothing left to run: nothing recorded again
    assert len(read_records(out)) == 2


def test_collect_on_ray_equals_local(ray_cluster, tmp_path, expert_store):
    from wamplan.data.store import EpisodeStore

    out = tmp_path / "expert"  # one episode (seed 0, one actor): each full expert episode costs ~15 s here
    assert main(["collect", "--source", "expert", "--episodes", "1", "--out", str(out), "--camera-size", "64",
                 "--ray", "--workers", "2"]) == 0
    mine, theirs = EpisodeStore(out), EpisodeStore(expert_store)
    assert [p.name for p in mine.episode_paths()] == [p.name for p in theirs.episode_paths()][:1]
    for a, b in zip(mine.episode_paths(), theirs.episode_paths()):
        ea, eb = mine.load(a), theirs.load(b)
        for name in ("actions", "proprio", "stages", "cube_pose", "tcp_pose", "sim_state", "image_steps"):
            np.testing.assert_array_equal(getattr(ea, name), getattr(eb, name), err_msg=name)
        # The drive targets at reset are the previous episode's last ones (zeros in a fresh env): they depend on
        # which episode a worker ran before, with worker processes as on Ray. From step 1 on they are the episode's.
        np.testing.assert_array_equal(ea.drive_targets[1:], eb.drive_targets[1:])
        assert ea.images.keys() == eb.images.keys()
        for cam in ea.images:
            np.testing.assert_array_equal(ea.images[cam], eb.images[cam], err_msg=cam)
        assert (ea.seed, ea.source, ea.success, ea.outcome, ea.reached, ea.policy) == \
            (eb.seed, eb.source, eb.success, eb.outcome, eb.reached, eb.policy)
        assert untimed(ea.provenance) == untimed(eb.provenance)
    assert main(["collect", "--source", "expert", "--episodes", "1", "--out", str(out), "--camera-size", "64",
                 "--ray"]) == 0  # resumed: nothing collected twice (the store refuses to overwrite)


class DiesOnce:
    """Times ten; the first attempt at item 1 kills its own process (a worker lost mid-item)."""

    def __init__(self, marker: str):
        self.marker = marker

    def __call__(self, item: int) -> tuple[int, int]:
        if item == 1 and not os.path.exists(self.marker):
            open(self.marker, "w").close()
            os._exit(1)
        return item, item * 10


def test_dead_actor_is_restarted_and_its_item_retried_once(ray_cluster, tmp_path):
    marker = str(tmp_path / "died")
    # one actor (one process to start, then its restart): it runs item 0, dies on item 1, is restarted, retries
    # item 1 and goes on to item 2
    results = list(imap_workers(lambda: DiesOnce(marker), [0, 1, 2], workers=1, backend=Backend("ray")))
    assert os.path.exists(marker)  # the first attempt at item 1 did die
    assert sorted(results) == [(0, 0), (1, 10), (2, 20)]  # every item once


class AlwaysDies:
    """A worker whose process dies on every item."""

    def __call__(self, item: int) -> int:
        os._exit(1)


def test_restarts_used_up_fail_in_one_line(ray_cluster):
    with pytest.raises(RuntimeError, match=r"its 1 restart\(s\) are used up .* re-run the same command to resume"):
        list(imap_workers(AlwaysDies, [0], workers=1, backend=Backend("ray", retries=1)))


def no_checkpoint():
    from wamplan.errors import UserError

    raise UserError("--wam /nowhere does not exist; train one with `wamplan wam train` or fix the path")


def test_a_worker_that_cannot_start_fails_in_one_line(ray_cluster):
    from wamplan.errors import UserError

    with pytest.raises(UserError) as e:
        list(imap_workers(no_checkpoint, [0, 1], workers=1, backend=Backend("ray")))  # one actor: one process
    assert str(e.value) == "--wam /nowhere does not exist; train one with `wamplan wam train` or fix the path"


def test_ray_missing_fails_in_one_line(monkeypatch, capsys, tmp_path):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError, as where it is not installed
    assert main([*EVAL, "--out", str(tmp_path / "e"), "--ray"]) == 2
    assert main(["collect", "--source", "expert", "--episodes", "1", "--out", str(tmp_path / "c"), "--ray"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all("pip install 'wamplan[ray]'" in line for line in err)
    assert not (tmp_path / "e").exists() and not (tmp_path / "c").exists()  # failed before writing anything


def test_backend_options():
    assert Backend.from_option(None) == Backend() and Backend.from_option("") == Backend("ray")
    assert Backend.from_option("auto") == Backend("ray", "auto")
    with pytest.raises(ValueError, match="one of"):
        Backend("dask")
    with pytest.raises(ValueError, match="only for the ray backend"):
        Backend("processes", "auto")


def test_worker_threads_split_the_cores_and_keep_under_omp_num_threads(monkeypatch):
    """Process workers share the cores, and a user's OMP_NUM_THREADS caps each (jobs started side by side)."""
    from wamplan.parallel import threads_per_worker

    monkeypatch.setattr("os.cpu_count", lambda: 16)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert [threads_per_worker(n) for n in (1, 2, 3, 16, 32)] == [16, 8, 5, 1, 1]
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert threads_per_worker(2) == 1
    monkeypatch.setenv("OMP_NUM_THREADS", "4")
    assert [threads_per_worker(n) for n in (1, 2, 8)] == [4, 4, 2]
    monkeypatch.setenv("OMP_NUM_THREADS", "")  # unset-like values leave the even split
    assert threads_per_worker(2) == 8
