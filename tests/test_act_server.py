"""`wamplan wam serve` for real use: loopback by default, the shared secret, the size limit, /health, and
concurrent clients each getting their own answer (checked against the same TinyWAM called directly)."""

from __future__ import annotations

import inspect
import json
import logging
import threading
from pathlib import Path

import json_numpy
import numpy as np
import pytest
import requests
import torch

from wamplan.checkpoint import save_checkpoint
from wamplan.config import to_dict
from wamplan.envs.contract import CAMERAS, Observation
from wamplan.errors import UserError
from wamplan import serving
from wamplan.serving.runner import BackgroundServer
from wamplan.wam import protocol
from wamplan.wam.base import WAM, WAMOutput, WAMServerError, load_wam
from wamplan.wam.cosmos_client import CosmosClientConfig, CosmosPolicyClient
from wamplan.wam.server import create_app, serve
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
    for headers in ({}, {serving.SECRET_HEADER: "wrong"}, {"Authorization": "Bearer wrong"},
                    {"Authorization": SECRET}):
        r = post(guarded.url + protocol.ROUTE, body(0), **headers)
        assert r.status_code == 401
        assert r.json() == {"error": "missing or wrong shared secret: send it in the X-WAMplan-Secret header, as "
                                     "Authorization: Bearer or Api-Key (openpi's api_key), or as ?token=SECRET in the "
                                     "URL (the wamplan client reads $WAMPLAN_ACT_SECRET)"}
        assert "\n" not in r.text
    for headers in ({serving.SECRET_HEADER: SECRET}, {"Authorization": f"Bearer {SECRET}"},
                    {"Authorization": f"Api-Key {SECRET}"}):
        r = post(guarded.url + protocol.ROUTE, body(0), **headers)
        assert r.status_code == 200 and "actions" in json.loads(r.text)
    # a client that cannot send headers (upstream's) carries the secret in its server URL
    token = requests.utils.quote(SECRET)
    assert post(f"{guarded.url}{protocol.ROUTE}?token={token}", body(0)).status_code == 200
    assert post(f"{guarded.url}{protocol.ROUTE}?token=wrong", body(0)).status_code == 401
    want = load_wam(tiny_ckpt).predict(make_obs(1), "insert")
    act_url = guarded.url + protocol.ROUTE
    np.testing.assert_array_equal(client(act_url, secret=SECRET).predict(make_obs(1), "insert").actions, want.actions)
    monkeypatch.setenv(serving.SECRET_ENV, SECRET)  # the client's default
    np.testing.assert_array_equal(client(act_url).predict(make_obs(1), "insert").actions, want.actions)
    monkeypatch.delenv(serving.SECRET_ENV)
    with pytest.raises(WAMServerError, match=r"HTTP 401.*set \$WAMPLAN_ACT_SECRET"):
        client(guarded.url + protocol.ROUTE).predict(make_obs(1), "insert")


def test_no_secret_means_open(tiny_ckpt):
    with BackgroundServer(create_app(load_wam(tiny_ckpt), secret="")) as srv:
        assert post(srv.url + protocol.ROUTE, body(0)).status_code == 200


def test_request_size_limit(guarded):
    big = make_obs(2)
    big.images = {c: np.zeros((128, 128, 3), np.uint8) for c in CAMERAS}  # ~200 KB of json_numpy
    r = client(guarded.url + protocol.ROUTE, secret=SECRET)
    with pytest.raises(WAMServerError, match=r"too large \(HTTP 413\).*send_image_size.*--max-request-mb") as e:
        r.predict(big, "insert")
    assert "--wam-send-image-size" not in str(e.value)  # no command has that flag
    payload = b" " * (64 * 1024 + 1)
    for data in (payload, iter([payload[:40000], payload[40000:]])):  # with a Content-Length, and chunked
        resp = post(guarded.url + protocol.ROUTE, data, **{serving.SECRET_HEADER: SECRET})
        assert resp.status_code == 413 and "over the server's limit of 65536 bytes" in resp.json()["error"]
        assert "--max-request-mb" in resp.json()["error"] and "--wam-send-image-size" not in resp.json()["error"]
    ok = post(guarded.url + protocol.ROUTE, body(0), **{serving.SECRET_HEADER: SECRET})
    assert ok.status_code == 200  # ~10 KB: fine


def test_health_needs_no_secret(guarded):
    r = requests.get(guarded.health_url, timeout=10)
    assert r.status_code == 200
    assert r.json() == {"ok": True, "wam": "tinywam", "task": "cube-insertion", "chunk_length": 16, "action_dim": 5,
                        "cameras": list(CAMERAS), "image_size": 32}


def test_default_host_is_loopback():
    from wamplan.cli import build_parser

    args = build_parser().parse_args(["wam", "serve", "--ckpt", "x"])
    assert args.host == "127.0.0.1" and args.secret is None
    assert inspect.signature(serve).parameters["host"].default == "127.0.0.1"
    assert inspect.signature(BackgroundServer).parameters["host"].default == "127.0.0.1"



def test_contradicting_error_modes_are_refused_before_the_port_is_bound(capsys):
    from wamplan.cli import main

    assert main(["wam", "serve", "--ckpt", "x", "--errors", "http", "--bare-errors"]) == 2
    assert "--bare-errors is --errors upstream, which --errors http contradicts" in capsys.readouterr().err


def test_concurrent_clients_get_their_own_answers(guarded, tiny_ckpt):
    direct = load_wam(tiny_ckpt)
    n_threads, per_thread = 4, 5
    want = {i: direct.predict(make_obs(i), "insert") for i in range(n_threads * per_thread)}
    got: dict[int, np.ndarray] = {}
    errors: list[str] = []
    start = threading.Barrier(n_threads)

    def work(t: int) -> None:
        c = client(guarded.url + protocol.ROUTE, secret=SECRET)
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


# -- an unmodified upstream robot client ------------------------------------------------------------------
# Written from upstream's protocol (NVlabs/cosmos-policy run_aloha_eval.py, get_action_from_server): it posts the
# observation as json_numpy (ALOHA's 14-D float64 qpos as proprio, return_all_query_results) with no header, and
# reads "actions", "future_image_predictions" and "value_predictions" (plural) from a dict answer; any other
# answer is an error to it.
SHIPPED_TINYWAM = Path(__file__).resolve().parents[1] / "checkpoints" / "mini" / "tinywam"
ALL_KEYS = ("all_actions", "all_future_image_predictions", "all_value_predictions", "all_actions_by_depth",
            "all_future_image_predictions_by_depth", "all_value_predictions_by_depth")


def aloha_observation(seed: int, size: int = 224) -> dict:
    rng = np.random.default_rng(seed)
    obs = {k: rng.integers(0, 256, (size, size, 3), dtype=np.uint8)
           for k in ("primary_image", "left_wrist_image", "right_wrist_image")}
    obs["proprio"] = rng.uniform(-1, 1, 14)  # float64, as ALOHA's qpos
    obs["task_description"] = "insert the cube into the square hole"
    return obs


def upstream_get_action(url: str, observation: dict, return_all: bool = False, encoded: bool = False) -> dict:
    observation = dict(observation, return_all_query_results=return_all)
    text = json_numpy.dumps(observation)
    data = json.dumps({"encoded": text}) if encoded else text
    response = json_numpy.loads(requests.post(url, data=data, headers=protocol.JSON_HEADERS, timeout=60).text)
    if encoded:  # double-encoded: a JSON string holding the json_numpy text
        assert isinstance(response, str)
        response = json_numpy.loads(response)
    if not isinstance(response, dict):
        raise ValueError(f"Got unexpected server response of type {type(response)}")
    got = {k: response[k] for k in ("actions", "future_image_predictions", "value_predictions")}
    got.update({k: response.get(k) for k in ALL_KEYS}, raw=response)
    return got


@pytest.fixture(scope="module")
def shipped():
    wam = load_wam(SHIPPED_TINYWAM, device="cpu")
    with BackgroundServer(create_app(wam, secret=SECRET, fit_proprio=True)) as srv:  # ALOHA's 14-D qpos
        yield srv, wam


@pytest.mark.parametrize("return_all, encoded", [(False, False), (True, False), (False, True), (True, True)])
def test_an_upstream_client_parses_every_answer(shipped, return_all, encoded):
    srv, wam = shipped
    obs = aloha_observation(3)
    url = f"{srv.url}{protocol.ROUTE}?token={requests.utils.quote(SECRET)}"
    got = upstream_get_action(url, obs, return_all, encoded)
    actions = np.stack(got["actions"])  # a list of (A,) rows, as upstream sends them
    direct = wam.predict(Observation(step=0, proprio=obs["proprio"][:10].astype(np.float32),
                                     images={"front": obs["primary_image"], "side": obs["left_wrist_image"],
                                             "wrist": obs["right_wrist_image"]}), obs["task_description"])
    np.testing.assert_array_equal(actions, direct.actions)  # the 14-D proprio was truncated to the model's 10
    preds = got["future_image_predictions"]
    for name, cam in (("future_image", "front"), ("future_wrist_image", "side"), ("future_wrist_image2", "wrist")):
        np.testing.assert_array_equal(preds[name], direct.images[cam])
    assert got["value_predictions"] == got["raw"]["value_prediction"] == protocol.VALUE_STANDIN
    notes = got["raw"]["wamplan"]["notes"]
    assert any("proprio of 14 entries truncated to its first 10" in n for n in notes)
    assert any("predicts no value" in n for n in notes) and got["raw"]["wamplan"]["value_predicted"] is False
    if return_all:
        assert all(got[k] is not None and len(got[k]) == 1 for k in ALL_KEYS)
        np.testing.assert_array_equal(np.stack(got["all_actions"][0]), actions)
        np.testing.assert_array_equal(np.stack(got["all_actions_by_depth"][0][0]), actions)
        assert got["all_value_predictions"] == [protocol.VALUE_STANDIN]
    else:
        assert all(got[k] is None for k in ALL_KEYS)
    # wamplan's own client reads the stand-in as no value
    views = {"front": obs["primary_image"], "side": obs["left_wrist_image"], "wrist": obs["right_wrist_image"]}
    ours = Observation(step=0, proprio=np.zeros(10, np.float32), images=views)
    assert client(srv.url + protocol.ROUTE, secret=SECRET).predict(ours, "insert").value is None


def test_a_short_proprio_is_padded(shipped):
    srv, _ = shipped
    obs = dict(aloha_observation(4), proprio=np.ones(7))
    got = upstream_get_action(f"{srv.url}{protocol.ROUTE}?token={requests.utils.quote(SECRET)}", obs)
    assert any("proprio of 7 entries padded with zeros to 10" in n for n in got["raw"]["wamplan"]["notes"])


def test_a_proprio_of_another_length_is_refused_without_fit_proprio(shipped):
    _, wam = shipped
    with BackgroundServer(create_app(wam)) as srv:
        for n in (14, 7):
            r = requests.post(srv.url + protocol.ROUTE, data=json_numpy.dumps(dict(aloha_observation(4),
                                                                                  proprio=np.ones(n))))
            assert r.status_code == 400
            assert r.json()["error"].endswith(f"proprio has {n} entries; the model reads 10: send 10, or start the "
                                              f"server with --fit-proprio to pad it with zeros or truncate it")


def _bad_requests() -> dict[str, bytes]:
    good = aloha_observation(5, size=16)
    text = lambda **kw: json_numpy.dumps({**good, **kw}).encode()  # noqa: E731
    without = {k: v for k, v in good.items() if k != "right_wrist_image"}
    return {
        "not JSON": b"{not json",
        "a list": b"[1, 2]",
        "a missing image": json_numpy.dumps(without).encode(),
        "a float image": text(primary_image=np.zeros((16, 16, 3), np.float32) + 0.5),
        "a flat image": text(primary_image=np.zeros((16, 16), np.uint8)),
        "NaN proprio": text(proprio=np.full(14, np.nan)),
        "an empty proprio": text(proprio=np.zeros(0)),
        "a numeric task": text(task_description=3),
        "a bad return_all": text(return_all_query_results="yes"),
        "encoded plus other keys": json.dumps({"encoded": json_numpy.dumps(good), "proprio": [1]}).encode(),
        "encoded not a string": json.dumps({"encoded": 5}).encode(),
    }


@pytest.mark.parametrize("case", sorted(_bad_requests()))
def test_a_clients_mistake_is_a_4xx_with_its_reason(shipped, case):
    srv, _ = shipped
    r = post(srv.url + protocol.ROUTE, _bad_requests()[case], **{serving.SECRET_HEADER: SECRET})
    assert 400 <= r.status_code < 500, r.text
    assert r.json()["error"].startswith("bad /act request: ") and "\n" not in r.json()["error"]


def test_the_upstream_error_mode_answers_as_upstream_and_logs_what_it_answered(tiny_ckpt, caplog):
    with BackgroundServer(create_app(load_wam(tiny_ckpt), errors="upstream", secret=SECRET)) as srv:
        caplog.set_level(logging.WARNING, logger="wamplan.serving.refusals")
        for data, headers in ((_bad_requests()["a missing image"], {serving.SECRET_HEADER: SECRET}),
                              (body(0), {})):  # a malformed request; a missing secret
            r = post(srv.url + protocol.ROUTE, data, **headers)
            assert r.status_code == 200 and r.json() == "error"
            with pytest.raises(ValueError, match="unexpected server response"):  # what upstream's client does
                upstream_get_action(srv.url + protocol.ROUTE, aloha_observation(0, size=16))
        said = [r.getMessage() for r in caplog.records]
        assert any('answered HTTP 200 "error" (upstream error mode): bad /act request' in m for m in said)
        assert not any("HTTP 4" in m for m in said)  # the log says what was answered
    with pytest.raises(UserError, match="unknown error mode 'bare'"):
        create_app(load_wam(tiny_ckpt), errors="bare")


class Overshooting(WAM):
    """A WAM whose chunk leaves [-1, 1] in three entries."""

    name = "test-overshoot"

    def predict(self, obs: Observation, instruction: str) -> WAMOutput:
        actions = np.zeros((16, 5), np.float32)
        actions[0, :3] = (1.5, -1.2, 1.01)
        return WAMOutput(actions=actions, images={c: obs.images[c] for c in self.cameras}, value=0.5)


def test_clipped_actions_are_said_once_per_answer(caplog):
    with BackgroundServer(create_app(Overshooting(), fit_proprio=True)) as srv:  # ALOHA's 14-D qpos
        caplog.set_level(logging.WARNING, logger="wamplan.wam.server")
        got = upstream_get_action(srv.url + protocol.ROUTE, aloha_observation(1, size=16))
    actions = np.stack(got["actions"])
    assert actions[0, :3].tolist() == [1.0, -1.0, 1.0] and np.abs(actions).max() == 1.0
    clip_notes = [n for n in got["raw"]["wamplan"]["notes"] if "clipped" in n]
    assert clip_notes == ["3 of 80 action entries were outside [-1, 1] (max |a| = 1.5) and were clipped"]
    assert sum("were clipped" in r.getMessage() for r in caplog.records) == 1
    assert got["value_predictions"] == got["raw"]["value_prediction"] == 0.5
    assert "value_predicted" not in got["raw"]["wamplan"]


def test_serve_prints_the_field_map(tiny_ckpt, capsys, monkeypatch):
    from wamplan.cli.main import main
    import wamplan.wam.server as server

    monkeypatch.setattr(server, "serve", lambda *a, **kw: None)  # start-up only
    assert main(["wam", "serve", "--ckpt", str(tiny_ckpt), "--errors", "upstream"]) == 0
    out = capsys.readouterr().out
    assert 'failures answered HTTP 200 "error" (upstream error mode)' in out
    assert "request fields: primary_image -> front, left_wrist_image -> side, right_wrist_image -> wrist; " \
           "predictions: front -> future_image, side -> future_wrist_image, wrist -> future_wrist_image2; " \
           "proprio of another length than 10 refused (--fit-proprio pads or truncates it); 16 x 5 actions" in out
    assert main(["wam", "serve", "--ckpt", str(tiny_ckpt), "--fit-proprio"]) == 0
    assert "; proprio of another length than 10 padded with zeros or truncated (--fit-proprio); 16 x 5 actions" \
        in capsys.readouterr().out
