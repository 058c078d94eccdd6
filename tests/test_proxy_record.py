"""`wamplan serve --record DIR`: sessions written as episodes of an episode store, a killed proxy's episodes in
progress finalised by the next start, and `wm train` on what was recorded; the recorder's frame grid and gaps;
an unwritable record directory refused at start-up."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import json_numpy
import numpy as np
import requests

from wamplan.data.store import EpisodeStore
from wamplan.envs.spec import Observation, get_task
from wamplan.proxy.record import JOURNALS, Recorder
from wamplan.wam import protocol

CKPTS = Path(__file__).resolve().parents[1] / "checkpoints" / "mini"
WAM_CKPT, WM_CKPT = str(CKPTS / "tinywam"), str(CKPTS / "wm_augmented")
FIELDS = {"primary_image": "front", "left_wrist_image": "side", "right_wrist_image": "wrist"}  # no profile: by position
H, SIZE = 16, 64


def observation(robot: int, step: int) -> Observation:
    rng = np.random.default_rng(robot * 1000 + step)
    views = {c: rng.integers(0, 256, (SIZE, SIZE, 3), dtype=np.uint8) for c in FIELDS.values()}
    return Observation(step=step, proprio=rng.uniform(-0.5, 0.5, 10).astype(np.float32), images=views)


def fields(obs: Observation) -> dict:
    return {**{f: obs.images[c] for f, c in FIELDS.items()}, "proprio": obs.proprio}


def post(url: str, obs: Observation, **extra) -> dict:
    body = json_numpy.dumps({**fields(obs), "task_description": "insert the cube", **extra}).encode()
    r = requests.post(url, data=body, headers=protocol.JSON_HEADERS, timeout=120)
    assert r.status_code == 200, r.text
    return json_numpy.loads(r.text)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def serve(record: Path, port: int, log: Path) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "wamplan.cli", "serve", "--upstream", WAM_CKPT, "--world-model", WM_CKPT,
           "--device", "cpu", "--errors", "http", "--port", str(port), "--record", str(record)]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "WAMPLAN_ACT_SECRET": ""}
    proc = subprocess.Popen(cmd, stdout=open(log, "w"), stderr=subprocess.STDOUT, env=env)
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline:
        assert proc.poll() is None, log.read_text()
        try:
            if requests.get(f"http://127.0.0.1:{port}/health", timeout=2).ok:
                return proc
        except requests.ConnectionError:
            time.sleep(0.3)
    proc.kill()
    raise AssertionError(f"serve did not come up: {log.read_text()}")


def test_sessions_recorded_survive_a_killed_proxy_and_train_a_world_model(tmp_path):
    """Robot 1 runs a 6-boundary episode sending executed_actions, resets (its episode is written) and starts a second;
    robot 2 runs 4 boundaries sending nothing; the proxy is SIGKILLed; a restarted proxy finalises both episodes in
    progress as `interrupted` and names them; `wm train --frameskip 16` trains one step on the 3 episodes."""
    record, port = tmp_path / "rec", free_port()
    url = f"http://127.0.0.1:{port}/s/%s/act"
    proc = serve(record, port, tmp_path / "serve1.log")
    rng = np.random.default_rng(0)
    try:
        ran = [rng.uniform(-1, 1, (H, 5)).astype(np.float32) for _ in range(5)]  # what robot 1 says it ran
        for k in range(6):
            post(url % "arm1", observation(1, k * H), **({"executed_actions": ran[k - 1]} if k else {}))
        answered2 = [np.stack(post(url % "arm2", observation(2, k * H))["actions"]) for k in range(4)]  # (H, 5) each
        first = post(url % "arm1", observation(3, 0), reset=True)
        assert first["wamplan"]["new_episode"] == "reset"
        post(url % "arm1", observation(3, H))
        deadline = time.monotonic() + 60  # the reset episode is written in the background
        while not list((record / "episodes").glob("*.h5")) and time.monotonic() < deadline:
            time.sleep(0.1)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    store = EpisodeStore(record)
    assert [m["outcome"] for m in store.iter_meta()] == ["logged"]  # the 2 others are journals in progress
    assert len(list((record / JOURNALS).iterdir())) == 2

    proc = serve(record, port, tmp_path / "serve2.log")  # the restart finalises what the killed proxy left
    proc.send_signal(signal.SIGTERM)
    proc.wait(60)
    said = (tmp_path / "serve2.log").read_text()
    assert said.count("(interrupted: ") == 2 and "0000001-arm2 -> episodes/proxy_arm2-s0000001.h5" in said, said
    assert list((record / JOURNALS).iterdir()) == []

    eps = {(m["source"], m["seed"]): store.load(m["path"]) for m in store.iter_meta()}
    assert sorted(eps) == [("proxy:arm1", 0), ("proxy:arm1", 2), ("proxy:arm2", 1)]
    one, two, three = eps["proxy:arm1", 0], eps["proxy:arm2", 1], eps["proxy:arm1", 2]
    assert [e.outcome for e in (one, two, three)] == ["logged", "interrupted", "interrupted"]
    assert [e.length for e in (one, two, three)] == [5 * H, 3 * H, H]  # the chunk after the last boundary: not kept
    assert one.image_steps.tolist() == [0, 16, 32, 48, 64, 80] and one.images["front"].shape == (6, SIZE, SIZE, 3)
    np.testing.assert_array_equal(one.actions, np.concatenate(ran))  # the executed_actions sent
    np.testing.assert_array_equal(two.actions, np.clip(np.concatenate(answered2[:3]), -1, 1))  # the chunks answered
    for k in range(6):
        o = observation(1, k * H)
        np.testing.assert_array_equal(one.proprio[k * H], o.proprio)
        for cam in FIELDS.values():
            np.testing.assert_array_equal(one.images[cam][k], o.images[cam])
    np.testing.assert_array_equal(one.proprio[H + 5], observation(1, H).proprio)  # held between boundaries
    assert json.loads(json.dumps(one.provenance))["chunks_with_executed_actions"] == 5
    assert three.provenance["ended_by"].startswith("recovered") and three.provenance["session"] == "arm1"

    from wamplan.cli.main import main  # a boundary-history world model trained on the robot's logs

    assert main(["wm", "train", "--data", str(record), "--out", str(tmp_path / "wm"), "--frameskip", "16",
                 "--context", "1", "--horizon", "1", "--depth", "1", "--max-steps", "1", "--batch-size", "2"]) == 0
    cfg = json.loads((tmp_path / "wm" / "checkpoint" / "config.json").read_text())
    assert cfg["config"]["predictor"]["frameskip"] == 16


def test_the_recorder_keeps_in_chunk_frames_on_its_grid_and_cuts_an_episode_at_a_gap(tmp_path):
    task = get_task("cube-insertion")
    rec = Recorder(tmp_path / "rec", task, tuple(FIELDS.values()), H, every=4)
    arm = type("Session", (), {"key": "arm"})()  # the recorder reads a session's key and identity
    answered = [np.full((H, 5), k / 10, np.float32) for k in range(4)]
    rec.boundary(arm, observation(1, 0), answered[0])
    for off in (4, 8, 12, 6):  # 6 is off the grid: its proprio is kept, its views are not
        rec.frame(arm, observation(1, off))
    rec.boundary(arm, observation(1, 16), answered[1])
    rec.frame(arm, observation(1, 20))  # 24 and 28 never sent: the episode ends at 16, a new one starts at 32
    rec.boundary(arm, observation(1, 32), answered[2])
    rec.boundary(arm, observation(1, 48), answered[3])  # no grid frames sent: cut again
    rec.close()
    store = EpisodeStore(tmp_path / "rec")
    assert store.image_every == 4
    lengths = [(m["seed"], m["length"], m["frames"]) for m in store.iter_meta()]
    assert lengths == [(0, 16, 5)]  # 32 -> 48 and 48 alone hold no whole chunk on the grid: removed
    ep = store.load(store.episode_paths()[0])
    assert ep.image_steps.tolist() == [0, 4, 8, 12, 16]
    for i, s in enumerate((0, 4, 8, 12, 16)):
        np.testing.assert_array_equal(ep.images["side"][i], observation(1, s).images["side"])
    np.testing.assert_array_equal(ep.actions, answered[0])
    np.testing.assert_array_equal(ep.proprio[6], observation(1, 6).proprio)
    np.testing.assert_array_equal(ep.proprio[7], observation(1, 6).proprio)
    assert list((tmp_path / "rec" / JOURNALS).iterdir()) == []

    # a client that runs 5 steps of each chunk and asks again, recorded with --record-every 5: its boundaries
    part = Recorder(tmp_path / "part", task, tuple(FIELDS.values()), H, every=5)
    for k in range(4):
        part.boundary(arm, observation(2, 5 * k), answered[k])
    part.close()
    store = EpisodeStore(tmp_path / "part")
    ep = store.load(store.episode_paths()[0])
    assert ep.length == 15 and ep.image_steps.tolist() == [0, 5, 10, 15]
    np.testing.assert_array_equal(ep.actions, np.concatenate([a[:5] for a in answered[:3]]))  # what each ran


def test_a_record_directory_that_cannot_be_written_is_refused_at_start_up(tmp_path, capsys):
    from wamplan.cli.main import main

    (tmp_path / "file").write_text("")
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("")
    for bad, said in ((tmp_path / "file", "is a file, not a directory"),
                      (tmp_path / "file" / "rec", f"{tmp_path / 'file'} is a file, so no directory can be made"),
                      (tmp_path / "other", "exists and is not an episode store")):
        assert main(["serve", "--upstream", WAM_CKPT, "--world-model", WM_CKPT, "--device", "cpu",
                     "--port", str(free_port()), "--record", str(bad)]) == 2
        err = capsys.readouterr().err.strip()
        assert f"--record {bad}" in err and said in err and "\n" not in err, err


def test_a_running_proxys_journal_is_left_alone_and_a_damaged_boundary_ends_the_episode_before_it(tmp_path):
    task, cams = get_task("cube-insertion"), tuple(FIELDS.values())
    live = Recorder(tmp_path / "rec", task, cams, H)
    arm = type("Session", (), {"key": "arm"})()
    for k in range(3):
        live.boundary(arm, observation(1, k * H), np.zeros((H, 5), np.float32))
    second = Recorder(tmp_path / "rec", task, cams, H)  # a second proxy on the same directory
    assert second.recovered == ["0000000-arm: recorded by a proxy that still runs; left alone"]
    (journal,) = (tmp_path / "rec" / JOURNALS).iterdir()
    (journal / "b0000032.npz").write_bytes(b"torn")  # as if damaged on disk
    live._open.pop(arm).release()  # the first proxy dies without writing its episode: its lock goes with it
    third = Recorder(tmp_path / "rec", task, cams, H)
    assert third.recovered == ["0000000-arm -> episodes/proxy_arm-s0000000.h5 (interrupted: 16 steps, 2 frames; "
                               "b0000032.npz is damaged (not a whole .npz), the episode ends before it)"]
    assert [m["length"] for m in EpisodeStore(tmp_path / "rec").iter_meta()] == [H]
