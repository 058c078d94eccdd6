"""The planning proxy in front of an upstream that, like Cosmos Policy's own ``deploy.py`` server, has no ``/health``:
the start-up probe (one rest observation) and the fit check it feeds, refused in one line; request views far from the
world model's size refused; and a ``/health`` (and ``/healthz``) that tells the upstream's state: 503 with the reason
while it is stopped, never answers or answers POST with 405, 200 again once it is back."""

from __future__ import annotations

import socket
import time

import json_numpy
import numpy as np
import pytest
import requests
from fastapi import FastAPI, Request
from fastapi.responses import Response

from wamplan.errors import UserError
from wamplan.proxy.app import create_proxy_app
from wamplan.proxy.build import build_proxy, unchecked
from wamplan.proxy.config import ProxyConfig
from wamplan.serving.runner import BackgroundServer
from wamplan.wam import protocol

from test_proxy import WM_CKPT, observation, request  # noqa: I001

pytestmark = pytest.mark.usefixtures("one_thread")


def stand_in(chunk: int = 50, action_dim: int = 14, size: int = 224,
             views: tuple[str, ...] = protocol.RESPONSE_IMAGE_FIELDS, post: bool = True) -> tuple[FastAPI, list[dict]]:
    """An upstream answering as Cosmos Policy's ALOHA ``deploy.py`` does (``actions`` chunk x action_dim rows,
    ``future_image_predictions``, ``value_prediction``; no ``/health``), with arrays of the shapes given; ``post``
    False: its ``/act`` takes only GET, so a POST is answered 405. -> (app, the requests it got)."""
    app, seen = FastAPI(), []

    async def act(request: Request) -> Response:
        seen.append(json_numpy.loads(await request.body()))
        rng = np.random.default_rng(len(seen))
        answer = {"actions": [row for row in rng.uniform(-1, 1, (chunk, action_dim))],
                  "future_image_predictions": {v: rng.integers(0, 256, (size, size, 3), dtype=np.uint8) for v in views},
                  "value_prediction": 0.5}
        return Response(json_numpy.dumps(answer), media_type="application/json")

    app.add_api_route(protocol.ROUTE, act, methods=["POST"] if post else ["GET"])
    return app, seen


def test_an_aloha_shaped_upstream_without_health_is_refused_at_start_up_in_one_line(capsys):
    """Cosmos Policy's ALOHA server (50 x 14 actions, three 224-px views) in front of the cube's world model: the
    probe's answer is refused in one line, before anything is planned; with --profile cosmos-aloha the profile's
    sizes are refused before anything is sent."""
    from wamplan.cli.main import main

    app, seen = stand_in()
    with socket.socket() as s:  # a free port for serve (it refuses before listening)
        s.bind(("127.0.0.1", 0))
        port = str(s.getsockname()[1])
    with BackgroundServer(app) as up:
        code = main(["serve", "--upstream", up.url + "/act", "--world-model", WM_CKPT, "--device", "cpu",
                     "--port", port])
        err = capsys.readouterr().err.strip()
        assert code == 2 and len(err.splitlines()) == 1, err
        assert err == (f"wamplan: error: world model {WM_CKPT} does not fit the upstream WAM at {up.url}/act: it returns "
                       f"50-step chunks; the world model plans chunks of at most 16 steps (task cube-insertion's); "
                       f"put a WAM of that task upstream, or serve a world model made for the upstream's robot"), err
        assert len(seen) == 1  # the one probe: a rest observation of the request's shape
        assert set(seen[0]) >= {"primary_image", "left_wrist_image", "right_wrist_image", "proprio"}
        assert not np.asarray(seen[0]["proprio"]).any() and np.asarray(seen[0]["primary_image"]).shape == (64, 64, 3)
        assert main(["serve", "--upstream", up.url + "/act", "--world-model", WM_CKPT, "--device", "cpu",
                     "--port", port, "--profile", "cosmos-aloha"]) == 2
        assert "it returns 50-step chunks" in capsys.readouterr().err and len(seen) == 1


@pytest.mark.parametrize("shape, said", [
    (dict(chunk=16), "its actions have 14 columns, task cube-insertion's 5; the proxy would overwrite columns "
                     "[0, 1, 2, 3, 4] of another robot's actions"),
    (dict(chunk=16, action_dim=5, size=64, views=("future_image",)),
     "it predicts the views ['future_image'], not ['future_wrist_image', 'future_wrist_image2'] that the world model "
     "needs"),
    (dict(chunk=16, action_dim=5, size=1), "it predicts 1-px views, the world model's encoder reads 64 px"),
    (dict(chunk=2, action_dim=5, size=64), "its 2-step chunks are shorter than the world model's frameskip 4"),
])
def test_what_the_probe_shows_is_checked(shape, said):
    app, seen = stand_in(**shape)
    with BackgroundServer(app) as up:
        with pytest.raises(UserError) as e:
            build_proxy(ProxyConfig(upstream=up.url + "/act", world_model=WM_CKPT, device="cpu"))
    assert said in str(e.value) and "\n" not in str(e.value) and len(seen) == 1


def test_a_fitting_upstream_is_served_and_views_far_from_the_world_models_size_are_refused():
    app, seen = stand_in(chunk=16, action_dim=5, size=64)
    with BackgroundServer(app) as up:
        p = build_proxy(ProxyConfig(upstream=up.url + "/act", world_model=WM_CKPT, device="cpu", errors="http"))
        try:
            assert unchecked(p) is None and p.chunk == 16
            with BackgroundServer(create_proxy_app(p)) as srv:
                r = requests.get(srv.url + "/health", timeout=10)
                assert r.status_code == 200 and r.json()["upstream_ok"] is True
                assert r.json()["checked"] == "start-up probe" and len(seen) == 1  # the poll cost no inference
                ok = requests.post(srv.url + "/act", data=request(observation(1, 0)), timeout=60)
                assert ok.status_code == 200 and json_numpy.loads(ok.text)["wamplan"]["open_loop"] == "first-chunk"
                tiny = {f: np.zeros((1, 1, 3), np.uint8) for f in ("primary_image", "left_wrist_image",
                                                                   "right_wrist_image")}
                body = json_numpy.dumps({**tiny, "proprio": np.zeros(10), "task_description": "x"})
                bad = requests.post(srv.url + "/act", data=body, timeout=60)
                assert bad.status_code == 400 and len(seen) == 2  # refused before the upstream is asked
                assert bad.json()["error"] == ("bad /act request: request field 'primary_image' is a 1x1-px view; the "
                                               "world model reads 64-px views: send the camera's image at 64 px or "
                                               "more")
        finally:
            p.close()


def poll(url: str, status: int, deadline_s: float = 20.0) -> requests.Response:
    """GET ``url`` until it answers ``status`` (a refresh runs in the background after each stale poll)."""
    end = time.monotonic() + deadline_s
    while True:
        r = requests.get(url, timeout=10)
        if r.status_code == status or time.monotonic() > end:
            return r
        time.sleep(0.05)


def test_health_says_503_while_the_upstream_is_stopped_and_200_once_it_is_back():
    app, seen = stand_in(chunk=16, action_dim=5, size=64)
    up = BackgroundServer(app).start()
    port = up.port
    p = build_proxy(ProxyConfig(upstream=up.url + "/act", world_model=WM_CKPT, device="cpu", errors="http"))
    p.health.refresh_s = 0.2
    try:
        with BackgroundServer(create_proxy_app(p)) as srv:
            assert requests.get(srv.url + "/health", timeout=10).status_code == 200
            time.sleep(0.3)
            assert poll(srv.url + "/health", 200).status_code == 200 and len(seen) == 1  # polls: no inference
            up.stop()
            r = poll(srv.url + "/health", 503)
            assert r.status_code == 503 and r.json()["ok"] is False and "is not reachable" in r.json()["reason"]
            z = requests.get(srv.url + "/healthz", timeout=10)
            assert z.status_code == 503 and z.text.startswith("upstream down: the upstream WAM at")
            act = requests.post(srv.url + "/act", data=request(observation(2, 0)), timeout=60)
            assert act.status_code == 502 and "is not reachable" in act.json()["error"]
            assert requests.get(srv.url + "/health", timeout=10).json()["checked"] in ("/act", "health probe")
            up = BackgroundServer(stand_in(chunk=16, action_dim=5, size=64)[0], port=port).start()  # back up
            r = poll(srv.url + "/health", 200)
            assert r.status_code == 200 and r.json()["checked"] == "health probe", r.text
            assert requests.get(srv.url + "/healthz", timeout=10).text == "OK\n"
            assert requests.post(srv.url + "/act", data=request(observation(2, 0)), timeout=60).status_code == 200
    finally:
        up.stop()
        p.close()


def test_an_upstream_that_never_answers_or_answers_post_with_405_is_503_with_the_reason():
    with socket.socket() as hang:  # accepts connections (the kernel's backlog) and never answers
        hang.bind(("127.0.0.1", 0))
        hang.listen(8)
        url = f"http://127.0.0.1:{hang.getsockname()[1]}/act"
        p = build_proxy(ProxyConfig(upstream=url, world_model=WM_CKPT, device="cpu", upstream_timeout_s=1.0))
        try:
            assert unchecked(p).startswith(f"warning: the upstream WAM at {url} did not answer the start-up probe "
                                           f"(the upstream WAM at {url} did not answer within 1 s)")
            with BackgroundServer(create_proxy_app(p)) as srv:
                r = requests.get(srv.url + "/health", timeout=10)
                assert r.status_code == 503 and r.json()["reason"].endswith("did not answer within 1 s")
        finally:
            p.close()
    app, seen = stand_in(chunk=16, action_dim=5, size=64, post=False)
    with BackgroundServer(app) as up:
        p = build_proxy(ProxyConfig(upstream=up.url + "/act", world_model=WM_CKPT, device="cpu"))
        try:
            with BackgroundServer(create_proxy_app(p)) as srv:
                r = requests.get(srv.url + "/health", timeout=10)
                assert r.status_code == 503 and "answered HTTP 405" in r.json()["reason"]
                assert "checks" not in r.json() and r.json()["checked"] == "start-up probe"
        finally:
            p.close()
