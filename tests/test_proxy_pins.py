"""What the planning proxy does that no other test pinned (issue 75, "behaviour no test pins"), each asserted by
value: RoboArena's reset seed reaching the session, openpi's ``state`` never overwriting an explicit ``proprio``,
``--max-request-bytes`` reaching uvicorn's WebSocket limit, least-recently-used eviction with idleness counted from
the last use, an upstream with one action column too few refused, a plan past its budget finished before the
session's next request is read, a short proprio padded at its end, and an upstream that times out answered 504."""

from __future__ import annotations

import asyncio
import socket
import time
from types import SimpleNamespace

import msgpack
import numpy as np
import pytest
import websockets.sync.client
from fastapi import FastAPI, Request
from fastapi.responses import Response

from wamplan.envs.spec import Observation, get_task
from wamplan.errors import UserError
from wamplan.proxy.build import check_fit
from wamplan.proxy.openpi import RESET_REPLY, add_openpi_routes, as_request
from wamplan.proxy.sessions import Session, Sessions
from wamplan.proxy.upstream import HttpUpstream, UpstreamError, UpstreamShape
from wamplan.serving.runner import BackgroundServer
from wamplan.wam import protocol

FIELDS = ("primary_image", "left_wrist_image", "right_wrist_image")


def shape(**known) -> UpstreamShape:
    """What an upstream shows of itself: ``known``, the rest unknown."""
    unknown = dict(chunk_length=None, action_dim=None, cameras=None, image_size=None, task=None)
    return UpstreamShape(**{**unknown, **known})


def test_a_reset_message_passes_its_seed_to_the_session():
    restarts = []
    task = get_task("cube-insertion")
    fake = SimpleNamespace(  # what the WebSocket routes read of a Proxy
        cfg=SimpleNamespace(ws_fields=""), request_map={f: f for f in FIELDS}, cameras=task.cameras, task=task,
        upstream=SimpleNamespace(shape=shape()), summary=lambda: {},
        restart=lambda key, seed: restarts.append((key, seed)), sessions=SimpleNamespace(drop=lambda key: True),
        health=SimpleNamespace(read=lambda: {"ok": True}))
    app = FastAPI()
    add_openpi_routes(app, fake, None)
    with BackgroundServer(app) as srv, websockets.sync.client.connect(f"ws://{srv.host}:{srv.port}/s/arm") as ws:
        ws.recv()  # the metadata
        ws.send(msgpack.packb({"endpoint": "reset", "seed": 7}))
        assert ws.recv() == RESET_REPLY
        ws.send(msgpack.packb({"endpoint": "reset"}))
        assert ws.recv() == RESET_REPLY
    assert [seed for _, seed in restarts] == [7, None]
    assert restarts[0][0].startswith("arm/#ws-")  # the connection's own session


def test_openpis_state_stands_for_proprio_only_where_proprio_is_absent():
    images = {f: np.zeros((8, 8, 3), np.uint8) for f in FIELDS}
    mine, state = np.arange(10, dtype=np.float32), np.full(14, 9.0, np.float32)
    req = as_request({**images, "proprio": mine, "state": state, "prompt": "go"}, FIELDS, [])
    np.testing.assert_array_equal(req.proprio, mine)
    np.testing.assert_array_equal(as_request({**images, "state": state, "prompt": "go"}, FIELDS, []).proprio, state)


def test_max_request_bytes_reaches_the_websocket_limit(monkeypatch):
    """``serve --max-request-bytes N``: uvicorn is started with ``ws_max_size=N`` (a larger WebSocket message closes
    the connection), as /act bodies over N are refused."""
    import wamplan.proxy.app as app_mod
    import wamplan.proxy.build as build_mod
    import wamplan.serving.runner as runner
    from wamplan.cli.main import main

    fake = SimpleNamespace(upstream=SimpleNamespace(where="the test upstream"), describe=lambda: "", recorder=None,
                           request_map={f: f for f in FIELDS}, close=lambda: None)
    monkeypatch.setattr(build_mod, "build_proxy", lambda cfg, planning=None: fake)
    monkeypatch.setattr(build_mod, "unchecked", lambda proxy: None)
    monkeypatch.setattr(app_mod, "create_proxy_app", lambda proxy, secret=None: FastAPI())
    started = {}

    class Server:
        def __init__(self, config):
            started.update(config)

        def run(self, sockets):
            for s in sockets:
                s.close()

    monkeypatch.setattr(runner, "uvicorn", SimpleNamespace(Config=lambda app, **kw: kw, Server=Server))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = str(s.getsockname()[1])
    assert main(["serve", "--upstream", "http://127.0.0.1:1/act", "--world-model", "wm", "--device", "cpu",
                 "--port", port, "--max-request-bytes", "12345"]) == 0
    assert started["ws_max_size"] == 12345


def test_sessions_evict_the_least_recently_used_and_count_idleness_from_the_last_use(monkeypatch):
    clock = [100.0]
    monkeypatch.setattr("wamplan.proxy.sessions.time", SimpleNamespace(monotonic=lambda: clock[0]))
    gone = []
    table = Sessions(lambda key: Session(key, SimpleNamespace(reset=lambda seed: None), None), idle_s=10.0,
                     max_sessions=2, on_forget=lambda s, why: gone.append((s.key, why)))

    def at(t, key):
        clock[0] = t
        return table.get(key)[1]

    assert [at(100, "a"), at(101, "b"), at(102, "a")] == ["first-request", "first-request", None]
    assert at(103, "c") == "first-request"
    assert gone == [("b", "evicted")] and table.keys() == ["a", "c"]  # a was used after b
    # a, made at 100 and last used at 102: 9 s after its last use it is not idle (18 s after it was made)
    assert [at(111, "a"), at(118, "a"), at(129, "a")] == [None, None, "idle"]


def test_an_upstream_with_one_action_column_too_few_is_refused():
    task = get_task("cube-insertion")  # the world model's 5 action columns 0..4

    def fit(action_dim):
        check_fit(task, SimpleNamespace(where="the test upstream", shape=shape()), 16, (0, 1, 2, 3, 4),
                  task.cameras, 4, None, "wm", shape(chunk_length=16, action_dim=action_dim),
                  explicit_columns=True)

    fit(5)
    with pytest.raises(UserError, match=r"its actions have 4 columns, the world model's task cube-insertion takes "
                                        r"columns \[0, 1, 2, 3, 4\]"):
        fit(4)


def test_a_plan_past_its_budget_finishes_before_the_sessions_next_request_is_read():
    from test_proxy import WAM_CKPT, WM_CKPT, observation, request, fields
    from wamplan.proxy.build import build_proxy
    from wamplan.proxy.config import ProxyConfig

    p = build_proxy(ProxyConfig(upstream=WAM_CKPT, world_model=WM_CKPT, device="cpu", errors="http",
                                budget_ms=1.0))
    events = []
    make, catch_up = p._make_policy, p._catch_up

    def slow_policy(wam):
        policy = make(wam)
        plan = policy.plan_chunk

        def plan_chunk(obs):
            events.append(f"plan {obs.step}")
            if obs.step:
                time.sleep(0.5)  # past the budget
            out = plan(obs)
            events.append(f"planned {obs.step}")
            return out
        policy.plan_chunk = plan_chunk
        return policy

    p._make_policy = slow_policy
    p._catch_up = lambda session, ours, notes: (events.append(f"read {session.step}"), catch_up(session, ours, notes))
    try:
        answers = []
        for t in (0, 16, 32):
            extra = {"chunk_frames": {str(o): fields(observation(1, t - 16 + o)) for o in (4, 8, 12)}} if t else {}
            answers.append(protocol.decode_response(p.handle(request(observation(1, t), **extra))).wamplan)
        assert [a["open_loop"] for a in answers[:2]] == ["first-chunk", "over-budget"]
        assert events.index("planned 16") < events.index("read 32")  # the next request waited for it
    finally:
        p.close()


def test_a_short_proprio_is_padded_with_zeros_at_its_end_and_a_long_one_keeps_its_first_entries():
    short, note = protocol.fit_proprio(np.arange(1, 8, dtype=np.float32), 10, fit=True)
    np.testing.assert_array_equal(short, [1, 2, 3, 4, 5, 6, 7, 0, 0, 0])
    assert note == "proprio of 7 entries padded with zeros to 10, the model's size"
    long, _ = protocol.fit_proprio(np.arange(1, 15, dtype=np.float32), 10, fit=True)
    np.testing.assert_array_equal(long, np.arange(1, 11))
    with pytest.raises(protocol.ProtocolError, match="^proprio has 14 entries; the model reads 10: send 10, or start "
                                                     "the server with --fit-proprio"):
        protocol.fit_proprio(np.arange(1, 15, dtype=np.float32), 10)


def test_an_upstream_that_does_not_answer_in_time_is_504():
    app = FastAPI()

    async def act(request: Request) -> Response:
        await asyncio.sleep(3.0)
        return Response("{}", media_type="application/json")

    app.add_api_route(protocol.ROUTE, act, methods=["POST"])
    with BackgroundServer(app) as srv:
        up = HttpUpstream(srv.url + protocol.ROUTE, timeout_s=0.3)
        req = protocol.ActRequest(images={f: np.zeros((8, 8, 3), np.uint8) for f in FIELDS},
                                  proprio=np.zeros(10, np.float32), task_description="go")
        with pytest.raises(UpstreamError) as e:
            up.ask(req, Observation(step=0, proprio=np.zeros(10, np.float32)))
        up.close()
    assert e.value.status == 504 and "did not answer within 0.3 s" in e.value.message
