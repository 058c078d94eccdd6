"""`wamplan wam serve` for real use: loopback by default, the shared secret, the size limit, /health, and
concurrent clients each getting their own answer (checked against the same TinyWAM called directly)."""

from __future__ import annotations

import inspect
import json
import threading

import numpy as np
import pytest
import requests
import torch

from wamplan.checkpoint import save_checkpoint
from wamplan.config import to_dict
from wamplan.envs.contract import CAMERAS, Observation
from wamplan.wam import protocol
from wamplan.wam.base import WAMServerError, load_wam
from wamplan.wam.cosmos_client import CosmosClientConfig, CosmosPolicyClient
from wamplan.wam.server import BackgroundServer, create_app, serve
from wamplan.wam.tinywam import KIND as TINYWAM_KIND
from wamplan.wam.tinywam import TinyWAMConfig, TinyWAMNet

SECRET = "correct horse battery staple"
TINY = TinyWAMConfig(image_size=32, channels=(8, 16), latent_dim=32, trunk_dim=64,
                     residual=False).for_task("cube-insertion")


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory):
    torch.manual_seed(0)
    return save_checkpoint(tmp_path_factory.mktemp("tinywam") / "ckpt", TinyWAMNet(TINY),
                           {"model": to_dict(TINY)}, kind=TINYWAM_KIND)


@pytest.fixture(scope="module")
def guarded(tiny_ckpt):
    """A TinyWAM server that needs SECRET and takes bodies up to 64 KiB, on a free 127.0.0.1 port."""
    with BackgroundServer(create_app(load_wam(tiny_ckpt), secret=SECRET, max_request_bytes=64 * 1024)) as srv:
        yield srv


def make_obs(i: int) -> Observation:
    rng = np.random.default_rng(i)
    return Observation(step=0, proprio=rng.uniform(-1, 1, 10).astype(np.float32),
                       images={c: rng.integers(0, 256, (24, 32, 3), dtype=np.uint8) for c in CAMERAS})


def body(i: int) -> bytes:
    obs = make_obs(i)
    req = protocol.ActRequest(images={f: obs.images[c] for f, c in zip(protocol.REQUEST_IMAGE_FIELDS, CAMERAS)},
                              proprio=obs.proprio, task_description="insert")
    return protocol.encode_request(req).encode()


def post(url: str, data, **headers) -> requests.Response:
    return requests.post(url, data=data, headers={**protocol.JSON_HEADERS, **headers}, timeout=30)


def client(url: str, **kw) -> CosmosPolicyClient:
    return CosmosPolicyClient(CosmosClientConfig(url=url, retries=0, timeout_s=30), **kw)


def test_the_secret_is_enforced(guarded, tiny_ckpt, monkeypatch):
    for headers in ({}, {protocol.SECRET_HEADER: "wrong"}, {"Authorization": "Bearer wrong"},
                    {"Authorization": SECRET}):
        r = post(guarded.act_url, body(0), **headers)
        assert r.status_code == 401
        assert r.json() == {"error": "missing or wrong shared secret: send it in the X-WAMplan-Secret header "
                                     "(the wamplan client reads $WAMPLAN_ACT_SECRET)"}
        assert "\n" not in r.text
    for headers in ({protocol.SECRET_HEADER: SECRET}, {"Authorization": f"Bearer {SECRET}"}):
        r = post(guarded.act_url, body(0), **headers)
        assert r.status_code == 200 and "actions" in json.loads(r.text)
    want = load_wam(tiny_ckpt).predict(make_obs(1), "insert")
    np.testing.assert_array_equal(client(guarded.act_url, secret=SECRET).predict(make_obs(1), "insert").actions,
                                  want.actions)
    monkeypatch.setenv(protocol.SECRET_ENV, SECRET)  # the client's default
    np.testing.assert_array_equal(client(guarded.act_url).predict(make_obs(1), "insert").actions, want.actions)
    monkeypatch.delenv(protocol.SECRET_ENV)
    with pytest.raises(WAMServerError, match=r"HTTP 401.*set \$WAMPLAN_ACT_SECRET"):
        client(guarded.act_url).predict(make_obs(1), "insert")


def test_no_secret_means_open(tiny_ckpt):
    with BackgroundServer(create_app(load_wam(tiny_ckpt), secret="")) as srv:
        assert post(srv.act_url, body(0)).status_code == 200


def test_request_size_limit(guarded):
    big = make_obs(2)
    big.images = {c: np.zeros((128, 128, 3), np.uint8) for c in CAMERAS}  # ~200 KB of json_numpy
    r = client(guarded.act_url, secret=SECRET)
    with pytest.raises(WAMServerError, match=r"too large \(HTTP 413\).*send_image_size.*--max-request-mb") as e:
        r.predict(big, "insert")
    assert "--wam-send-image-size" not in str(e.value)  # no command has that flag
    payload = b" " * (64 * 1024 + 1)
    for data in (payload, iter([payload[:40000], payload[40000:]])):  # with a Content-Length, and chunked
        resp = post(guarded.act_url, data, **{protocol.SECRET_HEADER: SECRET})
        assert resp.status_code == 413 and "over the server's limit of 65536 bytes" in resp.json()["error"]
        assert "--max-request-mb" in resp.json()["error"] and "--wam-send-image-size" not in resp.json()["error"]
    assert post(guarded.act_url, body(0), **{protocol.SECRET_HEADER: SECRET}).status_code == 200  # ~10 KB: fine


def test_health_needs_no_secret(guarded):
    r = requests.get(guarded.health_url, timeout=10)
    assert r.status_code == 200
    assert r.json() == {"ok": True, "wam": "tinywam", "task": "cube-insertion", "chunk_length": 16,
                        "cameras": list(CAMERAS)}


def test_default_host_is_loopback():
    from wamplan.cli import build_parser

    args = build_parser().parse_args(["wam", "serve", "--ckpt", "x"])
    assert args.host == "127.0.0.1" and args.secret is None
    assert inspect.signature(serve).parameters["host"].default == "127.0.0.1"
    assert inspect.signature(BackgroundServer).parameters["host"].default == "127.0.0.1"


def test_concurrent_clients_get_their_own_answers(guarded, tiny_ckpt):
    direct = load_wam(tiny_ckpt)
    n_threads, per_thread = 4, 5
    want = {i: direct.predict(make_obs(i), "insert") for i in range(n_threads * per_thread)}
    got: dict[int, np.ndarray] = {}
    errors: list[str] = []
    start = threading.Barrier(n_threads)

    def work(t: int) -> None:
        c = client(guarded.act_url, secret=SECRET)
        start.wait()
        for k in range(per_thread):
            i = t * per_thread + k
            try:
                got[i] = c.predict(make_obs(i), "insert").actions
            except Exception as e:  # recorded, then asserted below
                errors.append(f"request {i}: {e}")

    threads = [threading.Thread(target=work, args=(t,)) for t in range(n_threads)]
    for th in threads:
        th.start()
    for th in threads:
        th.join(120)
    assert not errors and sorted(got) == sorted(want)
    for i in want:
        np.testing.assert_array_equal(got[i], want[i].actions)  # its own answer, not a neighbour's
    assert len({got[i].tobytes() for i in got}) == len(got)  # and the answers do differ between requests
