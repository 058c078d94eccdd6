"""The planning proxy (`wamplan serve`): sessions kept apart under concurrent robots, the same actions as the same
planned episode in process, open-loop answers that say why, the start-up fit check, upstream failures answered in
the error mode, and an upstream-style client parsing its answers."""

from __future__ import annotations

import dataclasses
import json
import socket
import threading
from collections import Counter
from pathlib import Path

import json_numpy
import numpy as np
import pytest
import requests
import torch

from wamplan.api import planned_policy
from wamplan.planning import CostConfig
from wamplan.checkpoint import save_checkpoint
from wamplan.config import to_dict
from wamplan.envs.spec import Observation
from wamplan.errors import UserError
from wamplan.proxy.app import create_proxy_app
from wamplan.proxy.build import build_proxy
from wamplan.proxy.config import ProxyConfig
from wamplan.proxy.upstream import Upstream, UpstreamError, UpstreamShape
from wamplan.serving.runner import BackgroundServer
from wamplan.wam import protocol
from wamplan.wam.base import load_wam
from wamplan.wam.server import create_app
from wamplan.worldmodel import WorldModelPredictor, load_predictor
from wamplan.worldmodel.load import KIND as PREDICTOR_KIND

CKPTS = Path(__file__).resolve().parents[1] / "checkpoints" / "mini"
WAM_CKPT, WM_CKPT = str(CKPTS / "tinywam"), str(CKPTS / "wm_augmented")
FIELDS = {"primary_image": "front", "left_wrist_image": "side", "right_wrist_image": "wrist"}
H, SIZE = 16, 64


def observation(client: int, step: int, images: bool = True) -> Observation:
    rng = np.random.default_rng(client * 1000 + step)
    views = {c: rng.integers(0, 256, (SIZE, SIZE, 3), dtype=np.uint8) for c in FIELDS.values()} if images else None
    return Observation(step=step, proprio=rng.uniform(-0.5, 0.5, 10).astype(np.float32), images=views)


def fields(obs: Observation) -> dict:
    return {**{f: obs.images[c] for f, c in FIELDS.items()}, "proprio": obs.proprio}


def request(obs: Observation, **extra) -> bytes:
    return json_numpy.dumps({**fields(obs), "task_description": "insert the cube into the square hole",
                             **extra}).encode()


def post(url: str, data: bytes) -> dict:
    r = requests.post(url, data=data, headers=protocol.JSON_HEADERS, timeout=120)
    assert r.status_code == 200, r.text
    return json_numpy.loads(r.text)


@pytest.fixture(scope="module")
def proxy():
    """A proxy of the shipped models whose world model reads only the frames it is sent (``--history seen``): what
    the tests below check; the default imagined history is tests/test_proxy_imagined.py's."""
    from wamplan.planning.policy_config import PlannedPolicyConfig

    p = build_proxy(ProxyConfig(upstream=WAM_CKPT, world_model=WM_CKPT, device="cpu", errors="http"),
                    planning={"policy": PlannedPolicyConfig(history="seen")})
    with BackgroundServer(create_proxy_app(p)) as srv:
        yield srv, p
    p.close()


def in_process_episode(client: int, chunks: int, world_model: str = WM_CKPT) -> np.ndarray:
    """The same episode planned in process (same WAM, world model, planner, seed) -> (chunks x H, A) actions."""
    policy = planned_policy(load_wam(WAM_CKPT, device="cpu"), world_model=world_model, device="cpu")
    policy.reset(seed=0)
    return np.stack([policy.act(observation(client, t, policy.wants_images(t))) for t in range(chunks * H)])


def drive(url: str, client: int, chunks: int, frames: bool = True) -> list[dict]:
    """An episode through the proxy: at each boundary the observation, and the frames seen during the chunk
    before (every 4th step, what the world model's history needs)."""
    answers = []
    for k in range(chunks):
        t = k * H
        extra = {}
        if frames and k:
            extra["chunk_frames"] = {str(off): fields(observation(client, t - H + off)) for off in (4, 8, 12)}
        answers.append(post(url, request(observation(client, t), **extra)))
    return answers


def test_eight_robots_keep_their_histories_apart_and_act_as_in_process(proxy):
    srv, p = proxy
    n, chunks = 8, 2
    got: dict[int, list[dict]] = {}
    errors: list[str] = []
    start = threading.Barrier(n)

    def robot(c: int) -> None:
        start.wait()
        try:
            got[c] = drive(f"{srv.url}/s/robot{c}/act", c, chunks)
        except Exception as e:  # asserted below
            errors.append(f"robot {c}: {e}")

    threads = [threading.Thread(target=robot, args=(c,)) for c in range(n)]
    for th in threads:
        th.start()
    for th in threads:
        th.join(600)
    assert not errors and sorted(got) == list(range(n))
    for c in range(n):
        answers = got[c]
        assert [a["wamplan"]["step"] for a in answers] == [0, 16]
        assert [a["wamplan"]["session"] for a in answers] == [f"robot{c}"] * chunks
        assert [a["wamplan"]["open_loop"] for a in answers] == ["first-chunk", None]
        want = in_process_episode(c, chunks)  # (32, 5)
        np.testing.assert_allclose(np.concatenate([np.stack(a["actions"]) for a in answers]), want, atol=1e-6)
    assert len({np.stack(got[c][1]["actions"]).tobytes() for c in range(n)}) == n  # each planned its own


def test_without_the_in_chunk_frames_the_chunk_runs_open_loop_and_says_why(proxy):
    srv, _ = proxy
    answers = drive(f"{srv.url}/s/blind/act", 3, 2, frames=False)
    report = answers[1]["wamplan"]
    assert report["open_loop"] == "no-history" and report["planned"] is False
    assert any("needs the frames at steps [8, 12]" in n and "chunk_frames" in n for n in report["notes"])
    direct = load_wam(WAM_CKPT, device="cpu").predict(observation(3, 16), "insert the cube into the square hole")
    np.testing.assert_array_equal(np.stack(answers[1]["actions"]), direct.actions)  # the WAM's own chunk


def test_reset_route_session_id_and_reset_field_start_new_episodes(proxy):
    srv, _ = proxy
    url = f"{srv.url}/s/r9/act"
    assert post(url, request(observation(9, 0)))["wamplan"]["step"] == 0
    assert post(url, request(observation(9, 16)))["wamplan"]["step"] == 16
    r = requests.post(f"{srv.url}/s/r9/reset", timeout=10).json()
    assert r == {"ok": True, "sessions_reset": 1}
    a = post(url, request(observation(9, 0)))["wamplan"]
    assert a["step"] == 0 and a["new_episode"] == "first-request"
    assert post(url, request(observation(9, 16), reset=True))["wamplan"]["new_episode"] == "reset"
    b = post(url, request(observation(9, 0), session_id="arena-1"))["wamplan"]
    assert b["session"] == "r9/arena-1" and b["step"] == 0
    assert post(url, request(observation(9, 16), session_id="arena-1"))["wamplan"]["step"] == 16


def test_a_plan_over_budget_answers_the_wams_chunk(tmp_path):
    p = build_proxy(ProxyConfig(upstream=WAM_CKPT, world_model=WM_CKPT, device="cpu", errors="http",
                                budget_ms=0.001))
    try:
        with BackgroundServer(create_proxy_app(p)) as srv:
            answers = drive(f"{srv.url}/act", 4, 3)
        assert [a["wamplan"]["open_loop"] for a in answers] == ["first-chunk", "over-budget", "over-budget"]
        assert "longer than the 0.001 ms budget" in answers[1]["wamplan"]["notes"][0]
    finally:
        p.close()


def test_an_upstream_server_behind_the_proxy_passes_its_fields_through():
    up = BackgroundServer(create_app(load_wam(WAM_CKPT, device="cpu"), fit_proprio=True)).start()  # ALOHA's 14-D
    p = build_proxy(ProxyConfig(upstream=up.url + protocol.ROUTE, world_model=WM_CKPT, device="cpu", fit_proprio=True))
    assert p.upstream.unreachable is None  # its /health answered
    try:
        with BackgroundServer(create_proxy_app(p, secret="s")) as srv:
            url = f"{srv.url}/act?token=s"
            obs = observation(5, 0)
            body = {**fields(obs), "proprio": np.concatenate([obs.proprio, np.zeros(4)]),  # ALOHA's 14-D
                    "task_description": "insert", "return_all_query_results": True}
            text = requests.post(url, data=json.dumps({"encoded": json_numpy.dumps(body)}), timeout=60).json()
            assert isinstance(text, str)  # double-encoded, as upstream answers an encoded request
            answer = json_numpy.loads(text)
            assert len(answer["all_actions"]) == 1 and answer["value_predictions"] == 0.0
            assert any("truncated" in n for n in answer["wamplan"]["upstream"]["notes"])
            assert answer["wamplan"]["open_loop"] == "first-chunk"
            up.stop()  # the upstream gone: answered in the error mode, as upstream's server answers a failure
            r = requests.post(url, data=request(observation(5, 16)), timeout=60)
            assert r.status_code == 200 and r.json() == "error"
    finally:
        up.stop()
        p.close()


def test_an_upstream_that_wants_a_secret_the_proxy_lacks_is_named_so(monkeypatch):
    monkeypatch.delenv("WAMPLAN_UPSTREAM_SECRET", raising=False)
    with BackgroundServer(create_app(load_wam(WAM_CKPT, device="cpu"), secret="u")) as up:
        for secret, said in ((None, "start serve with $WAMPLAN_UPSTREAM_SECRET set to it"),
                             ("wrong", "is not its own: set it to the upstream's")):
            if secret:
                monkeypatch.setenv("WAMPLAN_UPSTREAM_SECRET", secret)
            p = build_proxy(ProxyConfig(upstream=up.url + protocol.ROUTE, world_model=WM_CKPT, device="cpu",
                                        errors="http"))
            try:
                with BackgroundServer(create_proxy_app(p)) as srv:
                    r = requests.post(f"{srv.url}/act", data=request(observation(1, 0)), timeout=60)
                    assert r.status_code == 502 and said in r.text
            finally:
                p.close()


class Shaped(Upstream):
    def __init__(self, **shape):
        self.where = "the test upstream"
        self.shape = UpstreamShape(**{**dict(chunk_length=16, action_dim=5, cameras=("front", "side", "wrist"),
                                             image_size=64, task="cube-insertion"), **shape})

    def ask(self, req, obs):  # the start-up probe: an upstream that does not answer (its fit is checked later)
        raise UpstreamError(502, "the test upstream does not answer")


@pytest.mark.parametrize("shape, said", [
    (dict(chunk_length=50), "returns 50-step chunks, not 16"),  # --chunk-length 16 said otherwise
    (dict(chunk_length=2), "shorter than the world model's frameskip 4; plan with a world model whose frameskip "
                           "divides the chunk (`wamplan wm train --frameskip 2`)"),
    (dict(action_dim=3), "its actions have 3 columns"),
    (dict(cameras=("front",)), "predicts views of ['front']"),
    (dict(image_size=32), "predicts 32-px views, the world model's encoder reads 64 px"),
    (dict(task="push-cube"), "serve a world model made for 'push-cube' (--world-model)"),
])
def test_a_world_model_that_does_not_fit_the_upstream_is_refused_in_one_line(shape, said):
    cfg = ProxyConfig(upstream="http://127.0.0.1:1/act", world_model=WM_CKPT, device="cpu",
                      chunk_length=None if shape.get("chunk_length") == 2 else 16)
    with pytest.raises(UserError) as e:
        build_proxy(cfg, upstream=Shaped(**shape))
    assert said in str(e.value) and "does not fit" in str(e.value) and "\n" not in str(e.value)


def test_an_upstream_that_reports_no_chunk_length_gets_the_world_model_tasks():
    """A Cosmos Policy server reports no chunk length; without --chunk-length or a profile, the task's is used."""
    p = build_proxy(ProxyConfig(upstream="http://127.0.0.1:1/act", world_model=WM_CKPT, device="cpu"),
                    upstream=Shaped(chunk_length=None))
    assert p.chunk == 16

def test_an_upstream_nothing_answers_for_is_said_at_start_up():
    from wamplan.proxy.upstream import HttpUpstream

    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    up = HttpUpstream(f"http://127.0.0.1:{port}/act", timeout_s=2.0)
    assert up.unreachable == "ConnectionError" and up.shape.chunk_length is None
    up.close()


def test_bad_proxy_fields_are_4xx(proxy):
    srv, _ = proxy
    url = f"{srv.url}/s/bad/act"
    post(url, request(observation(1, 0)))
    for extra in (dict(chunk_frames={"40": fields(observation(1, 4))}), dict(executed_actions=np.zeros((17, 5))),
                  dict(chunk_frames={"4": {"proprio": np.zeros(10)}}), dict(seed="x")):
        r = requests.post(url, data=request(observation(1, 16), **extra), timeout=60)
        assert r.status_code == 400 and r.json()["error"].startswith("bad /act request"), r.text


def test_upstreams_eval_client_history_feeds_the_world_model_where_it_falls_on_its_frames():
    """Upstream's eval client sends proprio_history / images_history (N frames `spacing` steps apart, ending one
    spacing before the boundary); with a spacing of 4 they are the frames the shipped world model needs."""
    p = build_proxy(ProxyConfig(upstream=WAM_CKPT, world_model=WM_CKPT, device="cpu", errors="http",
                                history_spacing=4))
    try:
        with BackgroundServer(create_proxy_app(p)) as srv:
            c = 6
            first = post(f"{srv.url}/act", request(observation(c, 0)))
            past = [observation(c, s) for s in (4, 8, 12)]
            history = dict(proprio_history=[o.proprio.astype(np.float64) for o in past],
                           images_history=[o.images[cam] for cam in ("side", "wrist", "front") for o in past])
            second = post(f"{srv.url}/act", request(observation(c, 16), **history))
        assert second["wamplan"]["open_loop"] is None
        got = np.concatenate([np.stack(first["actions"]), np.stack(second["actions"])])
        np.testing.assert_allclose(got, in_process_episode(c, 2), atol=1e-6)
    finally:
        p.close()


def test_serve_refuses_a_world_model_that_does_not_fit_in_one_line(capsys):
    from wamplan.cli.main import main

    code = main(["serve", "--upstream", WAM_CKPT, "--world-model", WM_CKPT, "--chunk-length", "50", "--device", "cpu"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    assert "does not fit the WAM 'tinywam': it returns 16-step chunks, not 50" in err
    assert main(["serve", "--upstream", "htp://robot:8777/act", "--world-model", WM_CKPT]) == 2  # a mistyped scheme
    assert "only http:// and https:// URLs are reached" in capsys.readouterr().err
    for upstream, said in (("http://robot:8777", "names no route; a WAM server answers at /act: pass "
                                                  "http://robot:8777/act"),
                           ("http://robot:8777/?k=v", "pass http://robot:8777/act?k=v"),
                           ("robot:8777/act", "looks like an address without its scheme; pass http://robot:8777/act")):
        assert main(["serve", "--upstream", upstream, "--world-model", WM_CKPT]) == 2
        assert said in capsys.readouterr().err


def test_the_proxy_plans_with_the_planner_cost_and_rules_it_is_given():
    """`serve --planner cem --num-candidates 8 --cost-view-weights 0 0 1` plans as the same settings in process."""
    planning = dict(planner="cem", planner_config={"num_candidates": 8, "num_elites": 2},
                    cost=CostConfig(view_weights=(0.0, 0.0, 1.0)))
    p = build_proxy(ProxyConfig(upstream=WAM_CKPT, world_model=WM_CKPT, device="cpu", errors="http"),
                    planning=planning)
    try:
        with BackgroundServer(create_proxy_app(p)) as srv:
            answers = drive(f"{srv.url}/s/cem/act", 5, 2)
        policy = planned_policy(load_wam(WAM_CKPT, device="cpu"), WM_CKPT, device="cpu", **planning)
        policy.reset(seed=0)
        want = np.stack([policy.act(observation(5, t, policy.wants_images(t))) for t in range(2 * H)])  # (32, 5)
        got = np.concatenate([np.stack(a["actions"]) for a in answers])
        np.testing.assert_allclose(got, want, atol=1e-6)
        assert answers[1]["wamplan"]["open_loop"] is None
        np.testing.assert_raises(AssertionError, np.testing.assert_allclose, got, in_process_episode(5, 2), atol=1e-6)
    finally:
        p.close()


def test_the_proxy_rolls_the_world_model_out_in_the_dtype_it_is_given():
    p = build_proxy(ProxyConfig(upstream=WAM_CKPT, world_model=WM_CKPT, device="cpu", wm_dtype="bfloat16"))
    try:
        assert p.dynamics.dtype == torch.bfloat16
    finally:
        p.close()


@pytest.mark.parametrize("flags, said", [
    (["--cost-view-weights", "1", "1"], "--cost-view-weights gives 2 weights, but task 'cube-insertion' has 3 "
                                        "cameras"),
    (["--num-elites", "4"], "--num-elites is an option of planner(s) ['cem', 'cem-gripper'], not of 'wamplan'"),
    (["--planner", "cem-gripper", "--gripper-dim", "9"], "gripper_dim 9 is not an entry of task 'cube-insertion''s"),
])
def test_serve_refuses_planning_settings_that_do_not_fit_in_one_line(capsys, flags, said):
    from wamplan.cli.main import main

    code = main(["serve", "--upstream", WAM_CKPT, "--world-model", WM_CKPT, "--device", "cpu", *flags])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and said in err, err


def test_serve_refuses_several_world_models_in_one_line(capsys):
    """An ensemble (A+B, A,B) left the core: refused at start-up, before anything loads, naming the fix."""
    from wamplan.cli.main import main

    for joined in (f"{WM_CKPT}+{WM_CKPT}", f"{WM_CKPT},{WM_CKPT}"):
        code = main(["serve", "--upstream", WAM_CKPT, "--world-model", joined, "--device", "cpu"])
        err = capsys.readouterr().err.strip()
        assert code == 2 and len(err.splitlines()) == 1, err
        assert f"--world-model {joined} joins 2 world models" in err and f"pass one checkpoint, e.g. --world-model " \
            f"{WM_CKPT}" in err, err


def test_an_episode_through_the_proxy_takes_the_in_process_episodes_actions(proxy, small_env):
    """A CubeInsertion-v1 episode (seed 1, three chunks) driven over HTTP, sending the frames seen during each chunk,
    takes the actions the same planned episode takes in process (same WAM, world model, planner, seed; no budget)."""
    from wamplan.policies.rollout import run_episode

    srv, _ = proxy
    env, seed, steps = small_env, 1, 3 * H
    policy = planned_policy(load_wam(WAM_CKPT, device="cpu"), world_model=WM_CKPT, device="cpu")
    want: list[np.ndarray] = []
    run_episode(env, policy, seed, max_steps=steps, stop_on_success=False,
                on_obs=lambda e, o, a: want.append(a) if a is not None else None)
    assert [c["planned"] for c in policy.info()["chunks"]] == [False, True, True]

    url, got, queue, seen = f"{srv.url}/s/sim/act", [], [], {}
    obs = env.reset(seed, with_images=True)
    for t in range(steps):
        if t % H == 0:
            extra = {"seed": seed} if t == 0 else {"chunk_frames": seen}
            answer = post(url, request(obs, **extra))
            assert answer["wamplan"]["step"] == t and answer["wamplan"]["planned"] == (t > 0)
            queue, seen = list(np.stack(answer["actions"])), {}
        action = env.check_action(queue.pop(0))
        got.append(action)
        obs, _ = env.step(action, with_images=(t + 1) % 4 == 0)
        if (t + 1) % H:
            if obs.images is not None:
                seen[str((t + 1) % H)] = fields(obs)
    np.testing.assert_allclose(np.stack(got), np.stack(want), atol=1e-6)

    # wamplan's own client does the same with send_chunk_frames (`eval --wam-url PROXY --wam-send-chunk-frames 4 8
    # 12`): condition 1's open-loop driver, its WAM the proxy, takes the planned episode's actions
    from wamplan.wam.base import WAMPolicy
    from wamplan.wam.cosmos_client import CosmosPolicyClient

    client = CosmosPolicyClient(url=f"{srv.url}/s/client/act", send_chunk_frames=(4, 8, 12))
    through: list[np.ndarray] = []
    driver = WAMPolicy(client)
    run_episode(env, driver, seed, max_steps=steps, stop_on_success=False,
                on_obs=lambda e, o, a: through.append(a) if a is not None else None)
    client.close()
    np.testing.assert_allclose(np.stack(through), np.stack(want), atol=1e-6)
    first = policy.info()["chunks"][0]["open_loop"]
    assert driver.info()["proxy"] == {first: 1, "planned": 2}  # what the proxy did, read from its answers

    # frames off the world model's grid (frameskip 4): the proxy plans nothing, and the driver's count and
    # `wamplan eval`'s closing line say so
    from wamplan.cli.eval import proxy_warning

    client = CosmosPolicyClient(url=f"{srv.url}/s/offgrid/act", send_chunk_frames=(5, 10))
    driver = WAMPolicy(client)
    run_episode(env, driver, seed, max_steps=steps, stop_on_success=False)
    client.close()
    assert driver.info()["proxy"] == {first: 1, "no-history": 2}
    assert proxy_warning(Counter(driver.info()["proxy"])) == (
        f"warning: the planning proxy planned none of the 3 chunks it answered (no-history 2, {first} 1) "
        f"(no-history: its world model lacked the in-chunk frames; send them with --wam-send-chunk-frames at "
        f"multiples of its frameskip, e.g. 4 8 12, as `wamplan serve`'s banner says)")


def test_a_boundary_retried_after_a_refusal_plans_as_if_sent_once(proxy):
    srv, _ = proxy
    c, url = 7, f"{srv.url}/s/retry/act"
    first = post(url, request(observation(c, 0)))
    frames = {str(off): fields(observation(c, off)) for off in (4, 8, 12)}
    bad = requests.post(url, data=request(observation(c, 16), chunk_frames={**frames, "40": frames["4"]}), timeout=60)
    assert bad.status_code == 400 and "offset '40'" in bad.json()["error"]
    second = post(url, request(observation(c, 16), chunk_frames=frames))
    assert second["wamplan"]["step"] == 16 and second["wamplan"]["planned"]
    third = post(url, request(observation(c, 32), chunk_frames={str(o): fields(observation(c, 16 + o))
                                                                for o in (4, 8, 12)}))
    got = np.concatenate([np.stack(a["actions"]) for a in (first, second, third)])
    np.testing.assert_allclose(got, in_process_episode(c, 3), atol=1e-6)  # chunk 2 reads chunk 1's actions


def boundary_world_model(out: Path, frameskip: int = H) -> str:
    """A world model whose frameskip is the chunk (Δ = 16), saved as `wm train --frameskip 16` saves one: the
    shipped predictor's weights where their shapes allow, a fresh action projector (its input is Δ·A wide)."""
    saved = json.loads((Path(WM_CKPT) / "config.json").read_text())["config"]
    shipped = load_predictor(WM_CKPT)
    cfg = dataclasses.replace(shipped.cfg, frameskip=frameskip)
    torch.manual_seed(0)
    model = WorldModelPredictor(cfg, shipped.task, shipped.cameras)
    own = model.state_dict()
    model.load_state_dict({k: v if v.shape == own[k].shape else own[k] for k, v in shipped.state_dict().items()})
    save_checkpoint(out, model, {**saved, "predictor": to_dict(cfg)}, kind=PREDICTOR_KIND)
    return str(out)


def test_a_boundary_world_model_plans_behind_a_client_that_posts_only_boundaries(tmp_path):
    """With Δ = the chunk the history of boundary t is t-32, t-16, t: what an unmodified client posts. The first
    chunk runs open loop (first-chunk), the second too (warm-up: its history reaches before step 0); from the third
    on every chunk is planned without chunk_frames, taking the actions of the same episode planned in process."""
    wm = boundary_world_model(tmp_path / "wm16")
    p = build_proxy(ProxyConfig(upstream=WAM_CKPT, world_model=wm, device="cpu", errors="http"))
    try:
        assert p.frameskip == H
        with BackgroundServer(create_proxy_app(p)) as srv:
            answers = drive(f"{srv.url}/s/plain/act", 8, 4, frames=False)
    finally:
        p.close()
    reports = [a["wamplan"] for a in answers]
    assert [r["open_loop"] for r in reports] == ["first-chunk", "warm-up", None, None]
    assert [r["planned"] for r in reports] == [False, False, True, True]
    assert not any("chunk_frames" in n for r in reports for n in r.get("notes", []))
    got = np.concatenate([np.stack(a["actions"]) for a in answers])  # (4 x H, A)
    np.testing.assert_allclose(got, in_process_episode(8, 4, wm), atol=1e-6)


def test_planning_refuses_a_frameskip_longer_than_the_chunk_in_one_line(tmp_path):
    from wamplan.planning.history import PlanningError

    wm = boundary_world_model(tmp_path / "wm32", frameskip=2 * H)
    with pytest.raises(PlanningError) as e:
        planned_policy(load_wam(WAM_CKPT, device="cpu"), world_model=wm, device="cpu")
    assert "frameskip 32 is longer than the WAM's 16-step chunk" in str(e.value) and "\n" not in str(e.value)
    assert "wamplan wm train --frameskip 16" in str(e.value)


def test_deploy_docs_world_model_from_robot_logs(tmp_path, monkeypatch):
    """docs/deploy.md's robot-log block, run on random logs: the store it writes trains a boundary world model of
    the robot's task; a log that does not fit the task is refused in one line."""
    import re

    from wamplan.cli.main import main
    from wamplan.data.store import EpisodeData, StoreError
    from wamplan.envs.spec import TASKS

    text = (Path(__file__).resolve().parents[1] / "docs" / "deploy.md").read_text()
    m = re.search(r"\*\*A world model for your robot\.\*\*.*?```py\n(.*?)```", text, re.DOTALL)
    assert m, "docs/deploy.md lost its robot-log block"
    rng = np.random.default_rng(0)
    steps = np.arange(0, 97, 4)  # (25,)
    logs = [dict(actions=rng.uniform(-1, 1, (96, 7)), proprio=rng.normal(size=(97, 8)), image_steps=steps,
                 images={c: rng.integers(0, 256, (len(steps), 32, 32, 3), np.uint8) for c in ("scene", "wrist")})
            for _ in range(6)]
    monkeypatch.chdir(tmp_path)
    try:
        scope = {"my_logs": logs}
        exec(compile(m.group(1), "deploy.md", "exec"), scope)
        assert main(["wm", "train", "--data", "data/my-arm", "--frameskip", "16", "--out", "runs/wm_my_arm",
                     "--epochs", "1", "--batch-size", "8", "--depth", "1"]) == 0
        cfg = json.loads((tmp_path / "runs/wm_my_arm/checkpoint/config.json").read_text())
        assert "my-arm" in json.dumps(cfg) and cfg["config"]["predictor"]["frameskip"] == 16
        with pytest.raises(StoreError, match=r"episode 9 does not fit task 'my-arm': proprio is \(96, 8\)"):
            EpisodeData.logged(scope["arm"], 9, logs[0]["actions"], logs[0]["proprio"][:-1], logs[0]["images"], steps)
        dropped = {c: v[[0, 1, 3]] for c, v in logs[0]["images"].items()}  # the frame at step 8 lost
        with pytest.raises(StoreError, match="step 8 missing or moved"):
            EpisodeData.logged(scope["arm"], 9, logs[0]["actions"][:12], logs[0]["proprio"][:13], dropped, [0, 4, 12])
    finally:
        dict.pop(TASKS, "my-arm", None)


def test_the_client_keeps_its_frames_and_episode_start_until_an_answer_is_read():
    """A request that fails (here one HTTP 500) is sent again whole: the chunk_frames, reset, seed and session_id of a
    client with send_chunk_frames reach the server with the retried request, and are sent only once answered."""
    from wamplan.wam.cosmos_client import CosmosPolicyClient

    class Flaky(requests.Session):  # the first POST answers HTTP 500, the others go through
        def __init__(self):
            super().__init__()
            self.trust_env, self.sent, self.failed = False, [], False

        def post(self, url, data=None, **kw):
            self.sent.append(json_numpy.loads(data))
            if not self.failed:
                self.failed = True
                bad = requests.Response()
                bad.status_code, bad._content = 500, b'{"error": "busy"}'
                return bad
            return super().post(url, data=data, **kw)

    with BackgroundServer(create_app(load_wam(WAM_CKPT, device="cpu"))) as srv:
        flaky = Flaky()
        client = CosmosPolicyClient(url=srv.url + protocol.ROUTE, send_chunk_frames=(4, 8, 12), session=flaky)
        client.begin_episode(7)
        obs = observation(1, 0)
        with pytest.raises(Exception, match="500"):
            client.predict(obs, "x")
        client.predict(obs, "x")  # the retry
        for t in (4, 8, 12):
            client.observe(observation(1, t))
        client.predict(observation(1, 16), "x")
    first, retry, second = flaky.sent
    for k in ("reset", "seed", "session_id"):
        assert first[k] == retry[k] and k in first, k
    assert first["seed"] == 7 and "reset" not in second and second["session_id"] == first["session_id"]
    assert sorted(second["chunk_frames"]) == ["12", "4", "8"] and "chunk_frames" not in first


def test_a_chunk_length_the_upstreams_health_contradicts_is_refused_at_start_up(proxy):
    srv, _ = proxy  # a wamplan server: its /health reports 16-step chunks
    with pytest.raises(UserError, match="returns 16-step chunks, not 8; drop --chunk-length or fix it"):
        build_proxy(ProxyConfig(upstream=f"{srv.url}/act", world_model=WM_CKPT, device="cpu", chunk_length=8))


def test_a_planned_chunk_refuses_missing_cameras_and_float_pixels_in_one_line():
    from wamplan.envs.spec import ObservationError

    policy = planned_policy(load_wam(WAM_CKPT, device="cpu"), world_model=WM_CKPT, device="cpu")
    policy.reset(seed=0)
    p = np.zeros(10, np.float32)
    hand = {c: np.zeros((64, 64, 3), np.uint8) for c in ("front", "side", "hand")}
    with pytest.raises(ObservationError, match=r"has no image for \['wrist'\] \(has \['front', 'hand', 'side'\]\)"):
        policy.plan_chunk(Observation(step=0, proprio=p, images=hand))
    floats = {c: np.full((64, 64, 3), 0.5, np.float32) for c in ("front", "side", "wrist")}
    with pytest.raises(ObservationError, match=r"the 'front' image is float32 of shape \(64, 64, 3\); give \(H, W, 3\) "
                                               r"uint8 pixels"):
        policy.plan_chunk(Observation(step=0, proprio=p, images=floats))
    with pytest.raises(ObservationError, match="TinyWAM.predict: the 'front' image is float32"):
        policy.wam.predict(Observation(step=0, proprio=p, images=floats), "x")
    with pytest.raises(TypeError, match="world_model must be a checkpoint directory"):
        planned_policy(policy.wam, world_model=None)
