"""openpi's WebSocket protocol on the planning proxy, driven by openpi's own client (``openpi-client``, unedited):
the metadata on connect, ALOHA-style observations renamed by ``--ws-fields``, the same planned actions as over
``/act``, one session per connection, RoboArena's ``endpoint: reset`` and ``session_id``, one-line errors that keep
the connection, and the secret as openpi's ``api_key``."""

from __future__ import annotations

import functools
import time

import msgpack
import numpy as np
import pytest
import requests
import websockets.sync.client
from websockets.exceptions import InvalidStatus

pytest.importorskip("openpi_client", reason="openpi's client is installed by scripts/setup.sh (make test)")
from openpi_client import msgpack_numpy  # noqa: E402
from openpi_client.websocket_client_policy import WebsocketClientPolicy  # noqa: E402

from wamplan.errors import UserError
from wamplan.proxy.app import create_proxy_app
from wamplan.proxy.build import build_proxy
from wamplan.proxy.config import ProxyConfig
from wamplan.proxy.config import parse_ws_fields
from wamplan.proxy.openpi import as_request, unpack, ws_fields_warning
from wamplan.serving.runner import BackgroundServer

from test_proxy import FIELDS, WAM_CKPT, WM_CKPT, H, in_process_episode, observation  # noqa: I001

pytestmark = pytest.mark.usefixtures("one_thread")

ALOHA = {"primary_image": "images/cam_high", "left_wrist_image": "images/cam_left_wrist",
         "right_wrist_image": "images/cam_right_wrist"}  # our field -> where openpi's ALOHA client puts the view
WS_FIELDS = ",".join(f"{theirs}={ours}" for ours, theirs in ALOHA.items())


def aloha(client: int, step: int) -> dict:
    """``observation(client, step)`` as openpi's ALOHA client sends it: nested images, channels first, 14-D state."""
    obs = observation(client, step)
    images = {theirs.split("/")[1]: np.ascontiguousarray(obs.images[FIELDS[ours]].transpose(2, 0, 1))
              for ours, theirs in ALOHA.items()}  # (3, H, W)
    return {"images": images, "state": np.concatenate([obs.proprio, np.zeros(4, np.float32)]),
            "prompt": "insert the cube into the square hole"}


@pytest.fixture(scope="module")
def proxy():
    p = build_proxy(ProxyConfig(upstream=WAM_CKPT, world_model=WM_CKPT, device="cpu", ws_fields=WS_FIELDS,
                                fit_proprio=True))  # ALOHA's 14-D state
    with BackgroundServer(create_proxy_app(p, secret="s3cret")) as srv:
        yield srv, p
    p.close()


def connect(srv, path: str = "") -> WebsocketClientPolicy:
    return WebsocketClientPolicy(host=f"ws://{srv.host}:{srv.port}{path}", api_key="s3cret")


def test_openpis_client_gets_planned_chunks_as_the_same_episode_in_process(proxy):
    srv, p = proxy
    client = connect(srv, "/s/arm")
    meta = client.get_server_metadata()
    assert meta["chunk_length"] == H and meta["image_fields"] == FIELDS and meta["needs_session_id"] is False
    answers = []
    for k in range(2):
        obs = aloha(4, k * H)
        if k:  # the frames seen during the chunk before, in the client's own layout
            obs["chunk_frames"] = {str(off): aloha(4, (k - 1) * H + off) for off in (4, 8, 12)}
        answers.append(client.infer(obs))
    assert [a["wamplan"]["open_loop"] for a in answers] == ["first-chunk", None]
    assert all(a["actions"].dtype == np.float32 and a["actions"].shape == (H, 5) for a in answers)
    assert answers[0]["wamplan"]["session"].startswith("arm/#ws-") and answers[1]["server_timing"]["infer_ms"] > 0
    assert set(answers[0]["future_image_predictions"]) >= {"future_image", "future_wrist_image"}
    np.testing.assert_allclose(np.concatenate([a["actions"] for a in answers]), in_process_episode(4, 2), atol=1e-6)


def test_each_connection_is_its_own_episode_and_is_forgotten_when_it_closes(proxy):
    srv, p = proxy
    first, second = connect(srv), connect(srv)
    a = first.infer(aloha(1, 0))["wamplan"]
    assert first.infer(aloha(1, 16))["wamplan"]["step"] == 16
    b = second.infer(aloha(2, 0))["wamplan"]
    assert (b["step"], b["new_episode"]) == (0, "first-request") and a["session"] != b["session"]
    before = len(p.sessions)
    first._ws.close()  # the client has no close(); its connection is what a robot process's exit closes
    second._ws.close()
    deadline = time.monotonic() + 10
    while len(p.sessions) > before - 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert len(p.sessions) == before - 2


def test_roboarenas_reset_endpoint_and_session_id(proxy):
    srv, _ = proxy
    headers = {"Authorization": "Api-Key s3cret"}
    with websockets.sync.client.connect(f"ws://{srv.host}:{srv.port}", additional_headers=headers) as ws:
        msgpack_numpy.unpackb(ws.recv())  # the metadata
        ask = lambda obs: msgpack_numpy.unpackb((ws.send(msgpack_numpy.packb(obs)), ws.recv())[1])  # noqa: E731
        sid = np.array(["ev-7"])  # RoboArena may send the id as a (1,) array
        assert ask({**aloha(3, 0), "endpoint": "infer", "session_id": sid})["wamplan"]["session"] == "default/ev-7"
        assert ask({**aloha(3, 16), "session_id": "ev-7"})["wamplan"]["step"] == 16
        ws.send(msgpack_numpy.packb({"endpoint": "reset", "session_id": sid, "seed": np.int64(5)}))
        assert ws.recv() == "reset successful"
        again = ask({**aloha(3, 0), "session_id": "ev-7"})["wamplan"]
        assert (again["step"], again["session"], again["new_episode"]) == (0, "default/ev-7", "reset")
        # RoboArena's evaluator names the session only on reset: the connection's own episode restarts
        own = [ask(aloha(3, t))["wamplan"] for t in (0, 16)]
        ws.send(msgpack_numpy.packb({"endpoint": "reset", "session_id": "never-sent-before"}))
        assert ws.recv() == "reset successful"
        after = ask(aloha(3, 0))["wamplan"]
        assert own[1]["step"] == 16 and (after["step"], after["new_episode"]) == (0, "reset")
        assert after["session"] == own[0]["session"] and after["session"].startswith("default/#ws-")


def test_observation_keys_numpy_scalars_and_joined_vectors_read_as_an_act_request():
    obs = {**aloha(0, 0), "grip": np.float32(0.25), "seed": np.int64(3), "extra/unmapped": np.zeros(2)}
    req = as_request(unpack(msgpack_numpy.packb(obs)), tuple(ALOHA), parse_ws_fields(f"{WS_FIELDS},state+grip=proprio"))
    assert req.proprio.shape == (15,) and req.proprio[-1] == np.float32(0.25)
    assert req.extra == {"seed": 3} and req.task_description == "insert the cube into the square hole"
    assert req.images["primary_image"].shape == (64, 64, 3)  # channels moved last


@pytest.mark.parametrize("message, said", [
    (b"\xc1 not msgpack", "not msgpack"),
    (msgpack.packb([1, 2]), "expected a dict"),
    (msgpack_numpy.packb({"endpoint": "plan"}), "endpoint 'plan' is not 'infer' or 'reset'"),
    (msgpack_numpy.packb({"state": np.zeros(14)}), "lacks ['images/cam_high'], which --ws-fields maps to"),
    (msgpack_numpy.packb({**aloha(0, 0), "prompt": 3}), "'task_description' is a int"),
    (msgpack.packb({"x": {"__ndarray__": True, "data": b"12", "dtype": "<f4", "shape": [4]}}), "array in the message"),
    (msgpack.packb(functools.reduce(lambda d, _: {"k": d}, range(50), {})), "nests dicts more than"),
    (msgpack_numpy.packb({**aloha(0, 0), "session_id": "#ws-1"}), "starts with '#'"),
    (msgpack_numpy.packb({"endpoint": "x" * 5000}), "is not 'infer' or 'reset'"),
    ("a text frame", "binary msgpack frame"),
])
def test_a_bad_message_gets_one_line_and_the_connection_stays_open(proxy, message, said):
    srv, _ = proxy
    with websockets.sync.client.connect(f"ws://{srv.host}:{srv.port}/?token=s3cret") as ws:
        ws.recv()
        ws.send(message)
        reply = ws.recv()
        assert isinstance(reply, str) and reply.startswith("wamplan proxy: ") and said in reply
        assert "\n" not in reply and len(reply) < 400
        ws.send(msgpack_numpy.packb(aloha(0, 0)))
        assert "actions" in msgpack_numpy.unpackb(ws.recv())


def test_a_wrong_secret_refuses_the_connection_and_healthz_answers(proxy):
    srv, _ = proxy
    with pytest.raises(InvalidStatus, match="401"):
        WebsocketClientPolicy(host=f"ws://{srv.host}:{srv.port}", api_key="wrong")
    with pytest.raises(InvalidStatus, match="401"):
        WebsocketClientPolicy(host=f"ws://{srv.host}:{srv.port}")
    assert requests.get(f"{srv.url}/healthz", timeout=10).text == "OK\n"


def test_ws_fields_are_checked_when_the_proxy_is_configured():
    with pytest.raises(UserError, match="--ws-fields entry 'state' is not FROM=TO"):
        ProxyConfig(upstream=WAM_CKPT, world_model=WM_CKPT, ws_fields="images/cam_high=primary_image,state")
    # a well-formed rename to a field nothing reads (a typo) is warned of at start-up, not refused (the upstream may read it)
    assert ws_fields_warning(f"{WS_FIELDS},state+grip=proprio,prompt=task_description", tuple(ALOHA)) is None
    line = ws_fields_warning(f"{WS_FIELDS},joints=propiro", tuple(ALOHA))
    assert line.startswith("warning: --ws-fields maps to ['propiro'], which the proxy does not read") and "'proprio'" in line


def test_roboarenas_evaluator_reads_the_world_models_cameras_and_the_tasks_action_space(proxy):
    """RoboArena's evaluation client (roboarena_evaluator evaluation_client/main.py) reads these keys of the metadata,
    with these defaults; the proxy's world model reads front, side and wrist; the cube's 5-D end-effector space has no
    RoboArena name, so action_space says what it is (and RoboArena's RobotEnv refuses it rather than drive joints)."""
    import dataclasses

    from wamplan.envs.spec import get_task
    from wamplan.proxy.openpi import roboarena_config

    srv, _ = proxy
    server_cfg = connect(srv).get_server_metadata()
    img_res = tuple(server_cfg["image_resolution"]) if server_cfg.get("image_resolution") else None
    needs_wrist = bool(server_cfg.get("needs_wrist_camera", True))
    n_external = int(server_cfg.get("n_external_cameras", 1))
    needs_stereo = bool(server_cfg.get("needs_stereo_camera", False))
    include_sid = bool(server_cfg.get("needs_session_id", False))
    action_space = server_cfg.get("action_space", "joint_position")
    assert (img_res, n_external, needs_wrist, needs_stereo, include_sid) == ((64, 64), 2, True, False, False)
    assert action_space == ("pd_ee_delta_xyzyaw (5-D, task cube-insertion; not a RoboArena action space: "
                            "joint_position, joint_velocity)")
    joints = dataclasses.replace(get_task("cube-insertion"), control_mode="pd_joint_pos")
    assert roboarena_config(("base_camera", "hand_camera"), joints) == {
        "n_external_cameras": 1, "needs_wrist_camera": True, "needs_stereo_camera": False,
        "action_space": "joint_position"}
    assert roboarena_config(("left", "right"), joints)["needs_wrist_camera"] is False
