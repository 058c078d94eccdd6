"""Episode videos (issue 74 items 1-3): `wamplan eval` films the first N seeds of every condition into OUT/videos
under c{condition}_seed{seed:04d}_{success|failure}[_plan].webm, a resume films the seeds it has not filmed and
nothing twice, the videos decode to frames of the expected size, a directory or codec that cannot take them is
refused before any episode, a filming failure keeps the record, and `wamplan film` puts two conditions of a seed
one above the other for the seeds they disagree on, re-running an unfilmed episode and checking its outcome.

Episodes are cut at 20 steps (chunk 0 open loop, chunk 1 planned at step 16) at 64 px with a tiny search."""

from __future__ import annotations

import errno
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path

import av
import numpy as np
import pytest

from wamplan.cli import main
from wamplan.evaluation.records import RECORDS, read_records

pytestmark = pytest.mark.usefixtures("one_thread")

CK = Path(__file__).parents[1] / "checkpoints" / "mini"
EVAL = ["eval", "--conditions", "1,7", "--seed-start", "0", "--wam", str(CK / "tinywam"), "--wm-augmented",
        str(CK / "wm_augmented"), "--camera-size", "64", "--max-steps", "20", "--num-candidates", "4", "--iterations",
        "1", "--decoder", str(CK / "decoder"), "--videos", "first2"]
SIZE = 160  # VideoConfig.video_size's default


def frames(path: Path) -> list[np.ndarray]:
    with av.open(str(path)) as f:
        assert f.streams.video[0].codec_context.name == "vp9"
        return [fr.to_ndarray(format="rgb24") for fr in f.decode(video=0)]


def names(run: Path) -> set[str]:
    return {p.name for p in (run / "videos").glob("*.webm")}


def expected(run: Path, seeds) -> set[str]:
    out = set()
    for r in read_records(run):
        if r["seed"] in seeds:
            tail = f"c{r['condition']}_seed{r['seed']:04d}_{'success' if r['success'] else 'failure'}"
            out |= {f"{tail}.webm"} | ({f"{tail}_plan.webm"} if r["condition"] == 7 else set())
    return out


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """One seed, then resumed to three: seeds 0 and 1 filmed (first2), seed 2 not; and the first run's videos."""
    out = tmp_path_factory.mktemp("videos") / "eval"
    assert main([*EVAL, "--episodes", "1", "--out", str(out)]) == 0
    first = {p.name: p.stat().st_mtime_ns for p in (out / "videos").glob("*.webm")}
    assert main([*EVAL, "--episodes", "3", "--out", str(out)]) == 0
    return out, first


def test_the_first_seeds_of_every_condition_are_filmed_and_a_resume_films_nothing_twice(run):
    out, first = run
    assert set(first) == expected(out, {0}) and len(first) == 3  # c1, c7 and c7's plan video of seed 0
    assert names(out) == expected(out, {0, 1})  # the resume filmed seed 1, not seed 2 (first2)
    assert {p.name: p.stat().st_mtime_ns for p in (out / "videos").glob("*.webm") if p.name in first} == first
    assert sorted((r["condition"], r["seed"]) for r in read_records(out)) == [(c, s) for c in (1, 7) for s in range(3)]
    assert not any(k.startswith("_video") for r in read_records(out) for k in r)  # the videos stay out of the records
    assert main([*EVAL, "--episodes", "3", "--out", str(out)]) == 0 and names(out) == expected(out, {0, 1})


def test_videos_decode_to_the_views_side_by_side_and_the_plan_to_one_picture_per_chunk(run):
    out, _ = run
    for name in expected(out, {0, 1}):
        pics = frames(out / "videos" / name)
        if name.endswith("_plan.webm"):  # chunks 0 (open loop) and 1 (planned), each a second, the last held
            # now | target | model, WAM's chunk | model, plan | real: 5 columns, a 30-px header over 3 views
            assert len(pics) == 3 and pics[0].shape == (30 + 3 * SIZE, 5 * SIZE, 3)
            model = pics[1][30:, 2 * SIZE:4 * SIZE].astype(int)
            assert model.std() > 5 and pics[0][30:, 2 * SIZE:4 * SIZE].std() < 5  # drawn when planned, grey before
        else:  # steps 0 and 16 (the policy's boundaries; c7 also 8 and 12, its history frames), 20 (the end), held
            assert len(pics) == (4 if name.startswith("c1") else 6) and pics[0].shape == (SIZE, 3 * SIZE, 3)
            assert pics[0].std() > 10  # a picture, not a blank


def test_a_video_directory_that_cannot_be_written_or_a_missing_codec_is_refused_before_any_episode(
        tmp_path, refused, monkeypatch):
    out = tmp_path / "eval"  # an evaluation directory whose videos/ is a file (a read-only one reads the same)
    out.mkdir()
    (out / RECORDS).write_text("")
    (out / "videos").write_text("in the way")
    refused([*EVAL, "--episodes", "1", "--out", out], "the video directory", "--videos none")
    assert sorted(p.name for p in out.iterdir()) == [RECORDS, "videos"]  # no settings stored, no episode run
    (out / "videos").unlink()
    (out / "videos").mkdir()
    real = tempfile.TemporaryFile  # a read-only videos/ (root writes through chmod): creating a file there fails

    def probe(*args, dir=None, **kwargs):
        if dir is not None and Path(dir).resolve() == (out / "videos").resolve():
            raise OSError(errno.EROFS, os.strerror(errno.EROFS))
        return real(*args, dir=dir, **kwargs)

    monkeypatch.setattr(tempfile, "TemporaryFile", probe)
    refused([*EVAL, "--episodes", "1", "--out", out], f"the video directory {out / 'videos'} cannot be written",
            "Read-only file system", "--videos none")
    assert sorted(p.name for p in out.iterdir()) == [RECORDS, "videos"]
    monkeypatch.undo()
    monkeypatch.setitem(sys.modules, "av", None)  # PyAV not installed
    refused([*EVAL, "--episodes", "1", "--out", tmp_path / "other"], "pip install av")
    assert not (tmp_path / "other").exists()
    monkeypatch.undo()
    refused([*EVAL[:-4], "--decoder", CK / "wm_augmented", "--episodes", "1", "--out", tmp_path / "third"],
            "not 'wm-decoder'")
    assert not (tmp_path / "third" / RECORDS).exists()
    refused([*EVAL[:-2], "--videos", "some", "--episodes", "1", "--out", tmp_path / "fourth"], "firstN")


def test_an_episode_whose_filming_fails_keeps_its_record(tmp_path, capsys):
    from contextlib import ExitStack

    from wamplan.envs.spec import Observation
    from wamplan.evaluation.filming import EpisodeFilm
    from wamplan.evaluation.runner import VIDEO_ERROR_KEY, VIDEO_KEY, _run_jobs
    from wamplan.evaluation.videos import VideoConfig
    from wamplan.parallel import Backend

    film = EpisodeFilm(object(), ("front", "side"), VideoConfig())
    obs = Observation(step=0, proprio=np.zeros(10, np.float32), images={"front": np.zeros((8, 8, 3), np.uint8)})
    film(None, obs, None)  # no "side" view: kept as the error, never raised into the episode
    assert film.error and "KeyError" in film.error and film.finish(None, 1) == {}
    rec = dict(condition=1, seed=4, variant="open-loop", success=False, outcome="never_lifted", length=3)
    jobs = [dict(rec), dict(rec, seed=5, **{VIDEO_KEY: {"episode": b"not a video dir"}})]
    (tmp_path / "videos").write_text("a file where the videos go")  # writing the second one's video fails

    def worker(job: dict) -> dict:  # what EvalWorker returns: seed 4's filming failed, seed 5's video came back
        return dict(job, **({VIDEO_ERROR_KEY: "KeyError: 'side'"} if job["seed"] == 4 else {}))

    got = list(_run_jobs(lambda: worker, jobs, tmp_path, 1, Backend(), ExitStack()))
    assert [r["seed"] for r in read_records(tmp_path)] == [4, 5] == [r["seed"] for r in got]
    assert not any(k.startswith("_video") for r in read_records(tmp_path) for k in r)
    err = capsys.readouterr().err
    assert "condition 1 seed 4 was not filmed (KeyError: 'side'); its record is kept" in err and "seed 5" in err


def test_film_pairs_the_seeds_the_conditions_disagree_on_and_checks_a_rerun(run, tmp_path, capsys):
    from wamplan.evaluation.pairs import disagreeing_seeds

    recs = [dict(condition=c, seed=s, success=ok, variant="open-loop") for c, s, ok in
            [(1, 0, True), (7, 0, True), (1, 1, False), (7, 1, True), (1, 2, True), (7, 2, False), (7, 3, True)]]
    assert disagreeing_seeds(recs, 1, 7) == [1, 2]  # seed 3: condition 1 never ran it
    src, _ = run
    out = shutil.copytree(src, tmp_path / "eval")
    assert main(["film", str(out)]) == 0  # every seed ended alike at 20 steps: nothing to film
    assert "agree on all 3 seeds" in capsys.readouterr().out
    lines = (out / RECORDS).read_text().splitlines()  # say condition 7 solved seed 1: the seeds now disagree
    lines = [json.dumps(dict(r, success=True, outcome="success")) if (r["condition"], r["seed"]) == (7, 1)
             else json.dumps(r) for r in map(json.loads, lines)]
    (out / RECORDS).write_text("\n".join(lines) + "\n")
    assert main(["film", str(out)]) == 0
    said = capsys.readouterr()
    summary = json.loads(said.out.strip().splitlines()[-1])
    assert summary == {"pairs": 1, "seeds": [1], "reruns_differing": 1}  # no c7_seed0001_success.webm: re-run
    assert "seed 1 condition 7 re-ran to never_lifted in 20 steps, but its record says success" in said.err
    pics = frames(out / "videos" / "pairs" / "seed0001_c1_vs_c7.webm")
    assert len(pics) >= 5 and pics[0].shape == (2 * (14 + SIZE), 3 * SIZE, 3)  # captioned, one above the other
    assert "c7_seed0001_failure.webm" in names(out)  # the re-run's video, named by the re-run's outcome
    assert main(["film", str(out), "--seeds", "7"]) == 2
    assert "no records of both conditions 1 and 7 for seeds [7]" in capsys.readouterr().err
