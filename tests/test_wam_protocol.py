"""The WAM interface, WAMPolicy, and the Cosmos Policy /act protocol (client <-> server over loopback HTTP)."""

from __future__ import annotations

import asyncio
import json
import socket

import json_numpy
import numpy as np
import pytest
import requests
import torch
from fastapi import FastAPI, Request
from fastapi.responses import Response

from wamplan.checkpoint import CheckpointError, save_checkpoint
from wamplan.config import ConfigError, to_dict
from wamplan.envs.contract import CAMERAS, Observation
from wamplan.errors import UserError
from wamplan.serving.refusals import error_reply
from wamplan.serving.runner import BackgroundServer
from wamplan.wam import protocol
from wamplan.wam.base import (
    DEFAULT_INSTRUCTION,
    WAM,
    WAMError,
    WAMOutput,
    WAMOutputError,
    WAMPolicy,
    WAMServerError,
    load_wam,
    make_wam,
    register_wam_loader,
    validate_wam_output,
)
from wamplan.wam.cosmos_client import CosmosClientConfig, CosmosPolicyClient, profile_config, resize_image
from wamplan.wam.profiles import PROFILES
from wamplan.wam.server import create_app
from wamplan.wam.tinywam import KIND as TINYWAM_KIND
from wamplan.wam.tinywam import TinyWAMConfig, TinyWAMNet

H, A = 16, 5
CHUNK = np.linspace(-0.9, 0.9, H * A, dtype=np.float32).reshape(H, A)  # (16, 5)


class EchoWAM(WAM):
    """Test double: a fixed chunk, and each camera's predicted image = the inverted input image."""

    name = "test-echo"

    def __init__(self, fail: bool = False, value: float | None = 0.25):
        self.fail, self.value = fail, value
        self.calls: list[tuple[Observation, str]] = []
        self.resets = 0

    def predict(self, obs: Observation, instruction: str) -> WAMOutput:
        self.calls.append((obs, instruction))
        if self.fail:
            raise RuntimeError("the model blew up")
        images = {c: 255 - obs.images[c] for c in self.cameras}  # (h, w, 3) uint8
        return WAMOutput(actions=(CHUNK + 0.01 * len(self.calls)).astype(np.float32), images=images,
                         value=self.value)

    def reset(self) -> None:
        self.resets += 1


def make_obs(step: int = 0, images: bool = True) -> Observation:
    rng = np.random.default_rng(step)
    imgs = {c: rng.integers(0, 256, (24, 32, 3), dtype=np.uint8) for c in CAMERAS} if images else None
    return Observation(step=step, proprio=np.arange(10, dtype=np.float32) / 10, images=imgs)


def client(url: str, **kw) -> CosmosPolicyClient:
    kw.setdefault("backoff_s", 0.01)
    kw.setdefault("timeout_s", 10.0)
    return CosmosPolicyClient(CosmosClientConfig(url=url, **kw))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# -- servers --------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def echo():
    wam = EchoWAM()
    with BackgroundServer(create_app(wam, instruction_default="default task")) as srv:
        yield srv, wam


# residual=False: the untrained model's images are its own (sigmoid of a random decoder), not the input views
TINY = TinyWAMConfig(image_size=32, channels=(8, 16), latent_dim=32, trunk_dim=64,
                     residual=False).for_task("cube-insertion")


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory):
    """An untrained, seeded TinyWAM saved as a checkpoint (what `wamplan wam serve --ckpt` loads)."""
    torch.manual_seed(0)
    net = TinyWAMNet(TINY)
    return save_checkpoint(tmp_path_factory.mktemp("tinywam") / "ckpt", net, {"model": to_dict(TINY)},
                           kind=TINYWAM_KIND)


@pytest.fixture(scope="module")
def tiny_server(tiny_ckpt):
    """`wamplan wam serve`'s app (load_wam + create_app) on a free 127.0.0.1 port, in-process."""
    with BackgroundServer(create_app(load_wam(tiny_ckpt))) as srv:
        yield srv


@pytest.fixture(scope="module")
def failing():
    with BackgroundServer(create_app(EchoWAM(fail=True))) as srv:
        yield srv


def good_answer(actions: np.ndarray | None = None, **changes) -> dict:
    rng = np.random.default_rng(7)
    ans = {
        "actions": [row for row in (np.linspace(-0.5, 0.5, H * 7, dtype=np.float32).reshape(H, 7)
                                    if actions is None else actions)],
        "future_image_predictions": {k: rng.integers(0, 256, (8, 8, 3), dtype=np.uint8)
                                     for k in protocol.RESPONSE_IMAGE_FIELDS},
        "value_prediction": 0.5,
    }
    ans.update(changes)
    return ans


def _preds(**over):
    p = good_answer()["future_image_predictions"]
    p.update(over)
    return p


# Answers shaped like the released Cosmos Policy models' (cosmos_policy constants: ALOHA 50 x 14 actions and
# 14-D proprio, RoboCasa 32 x 7 and 9-D proprio; images 224 px). ALOHA's deploy script sends each image with a
# leading batch axis (1, 224, 224, 3); RoboCasa predicts two third-person views and one wrist view.
ALOHA_ACTIONS = np.linspace(-0.95, 0.95, 50 * 14, dtype=np.float32).reshape(50, 14)  # (50, 14)
ROBOCASA_ACTIONS = np.linspace(0.9, -0.9, 32 * 7, dtype=np.float32).reshape(32, 7)  # (32, 7)


def _views(names, shape, seed):
    rng = np.random.default_rng(seed)
    return {k: rng.integers(0, 256, shape, dtype=np.uint8) for k in names}


ALOHA_IMAGES = _views(("future_image", "future_wrist_image", "future_wrist_image2"), (1, 224, 224, 3), 1)
ROBOCASA_IMAGES = _views(("future_image", "future_image2", "future_wrist_image"), (224, 224, 3), 2)
SHAPED = {
    "aloha": {"actions": list(ALOHA_ACTIONS), "future_image_predictions": ALOHA_IMAGES, "value_prediction": 0.8},
    "robocasa": {"actions": list(ROBOCASA_ACTIONS), "value_prediction": np.float32(0.3),
                 "future_image_predictions": {**ROBOCASA_IMAGES, "future_wrist_image2": None}},
    # a RoboCasa-style model fine-tuned on `wamplan data export`: 16 x 5 actions (the cosmos-robocasa profile)
    "wamplan-robocasa": {"actions": list(ROBOCASA_ACTIONS[:16, :5]), "value_prediction": 0.6,
                         "future_image_predictions": {**ROBOCASA_IMAGES, "future_wrist_image2": None}},
}


BAD_ANSWERS = {  # route -> (answer body, substring the client's error must contain)
    "short_chunk": (json_numpy.dumps(good_answer(np.zeros((8, 5), np.float32))), "returned 8-step chunks"),
    "few_dims": (json_numpy.dumps(good_answer(np.zeros((H, 3), np.float32))), "returned 3-D actions"),
    "nan": (json_numpy.dumps(good_answer(np.full((H, 7), np.nan, np.float32))), "non-finite"),
    "no_actions": (json_numpy.dumps({"future_image_predictions": _preds()}), "has no 'actions'"),
    "no_images": (json_numpy.dumps({"actions": np.zeros((H, 7), np.float32)}), "future_image_predictions"),
    "missing_view": (json_numpy.dumps(good_answer(future_image_predictions=_preds(future_wrist_image2=None))),
                     "no 'future_wrist_image2' image"),
    "float_image": (json_numpy.dumps(good_answer(future_image_predictions=_preds(
        future_image=np.zeros((8, 8, 3), np.float32)))), "expected uint8"),
    "flat_image": (json_numpy.dumps(good_answer(future_image_predictions=_preds(
        future_image=np.zeros((8, 8), np.uint8)))), "expected (h, w, 3)"),
    "ragged": (json_numpy.dumps(good_answer(actions=[[0.0] * 7] * 15 + [[0.0] * 6])), "not a numeric array"),
    "bare_list": (json_numpy.dumps([[0.0] * 5] * H), "bare action list"),
    "not_json": ("<html>oops</html>", "not valid json_numpy JSON"),
}


@pytest.fixture(scope="module")
def fake():
    """Endpoints that answer like a (mis)behaving Cosmos Policy server; /record/act keeps the request."""
    app = FastAPI()
    seen: dict[str, object] = {}

    @app.post("/{case}/act")
    async def act(case: str, request: Request) -> Response:
        body = await request.body()
        seen[case] = body
        if case == "slow":
            await asyncio.sleep(3.0)
        if case == "http500":
            return Response("internal failure", status_code=500)
        if case == "error":
            return Response(json.dumps("error"), media_type="application/json")
        if case in BAD_ANSWERS:
            return Response(BAD_ANSWERS[case][0], media_type="application/json")
        if case in SHAPED:
            return Response(json_numpy.dumps(SHAPED[case]), media_type="application/json")
        if case == "double":
            return Response(json.dumps(json_numpy.dumps(good_answer())), media_type="application/json")
        if case == "overshoot":
            return Response(json_numpy.dumps(good_answer(np.full((H, 5), 1.2, np.float32))),
                            media_type="application/json")
        return Response(json_numpy.dumps(good_answer()), media_type="application/json")

    with BackgroundServer(app) as srv:
        yield srv, seen


# -- round trips ----------------------------------------------------------------------------------------
def test_round_trip_over_http(echo):
    srv, wam = echo
    n0 = len(wam.calls)
    obs = make_obs()
    out = client(srv.url + protocol.ROUTE).predict(obs, "insert the cube")
    seen_obs, instruction = wam.calls[-1]
    assert len(wam.calls) == n0 + 1 and instruction == "insert the cube"
    np.testing.assert_array_equal(seen_obs.proprio, obs.proprio)
    for c in CAMERAS:
        np.testing.assert_array_equal(seen_obs.images[c], obs.images[c])  # request mapping inverted by server
        np.testing.assert_array_equal(out.images[c], 255 - obs.images[c])  # response mapping inverted by client
        assert out.images[c].dtype == np.uint8
    expected = (CHUNK + 0.01 * len(wam.calls)).astype(np.float32)
    assert out.actions.dtype == np.float32 and out.actions.shape == (H, A)
    np.testing.assert_array_equal(out.actions, expected)
    assert out.value == pytest.approx(0.25)
    assert out.timing["http_s"] <= out.timing["query_s"]  # the query = adapting + HTTP + decoding
    assert out.extras == {"attempts": 1, "url": srv.url + protocol.ROUTE}


def test_tinywam_round_trip_through_the_server_matches_calling_it_directly(tiny_server, tiny_ckpt):
    direct = load_wam(tiny_ckpt)  # a second copy of the same checkpoint, called in-process
    for step in (0, 5):
        obs = make_obs(step)  # 24 x 32 renders: TinyWAM resizes them to its 32 px on both paths
        want = direct.predict(obs, "insert the cube")
        got = client(tiny_server.url + protocol.ROUTE).predict(obs, "insert the cube")
        np.testing.assert_array_equal(got.actions, want.actions)  # float32 survives json_numpy exactly
        assert got.actions.shape == (H, A) and np.abs(got.actions).max() > 0.01  # a real, non-zero chunk
        assert got.value is None and want.value is None
        for c in CAMERAS:
            assert got.images[c].shape == (32, 32, 3)  # the WAM's resolution, not the renders'
            np.testing.assert_array_equal(got.images[c], want.images[c])
    # the predicted views are the model's, per camera: they differ from each other and between inputs
    assert not np.array_equal(got.images["front"], got.images["side"])
    other = client(tiny_server.url + protocol.ROUTE).predict(make_obs(0), "t")
    assert not np.array_equal(got.images["front"], other.images["front"])


def test_tinywam_server_with_a_custom_camera_mapping(tiny_server, tiny_ckpt):
    """Our side view sent as the server's primary image (its 'front') and so on: the server's model sees the
    permuted views, and the client maps its predictions back by response field."""
    direct = load_wam(tiny_ckpt)
    obs = make_obs(9)
    c = client(tiny_server.url + protocol.ROUTE,
               request_fields=("side=primary_image", "front=left_wrist_image", "wrist=right_wrist_image"),
               response_fields=("front=future_wrist_image", "wrist=future_image"))
    got = c.predict(obs, "t")
    permuted = Observation(step=0, proprio=obs.proprio,
                           images={"front": obs.images["side"], "side": obs.images["front"],
                                   "wrist": obs.images["wrist"]})
    want = direct.predict(permuted, "t")  # what the server's model computes
    np.testing.assert_array_equal(got.actions, want.actions)
    np.testing.assert_array_equal(got.images["front"], want.images["side"])  # future_wrist_image = its 'side'
    np.testing.assert_array_equal(got.images["wrist"], want.images["front"])  # future_image = its 'front'
    assert not np.array_equal(got.actions, direct.predict(obs, "t").actions)  # the permutation mattered


def test_aloha_shaped_answer_mapped_by_the_client(fake):
    srv, seen = fake
    cols = (7, 8, 9, 12, 13)  # e.g. the right arm's x, y, z, a wrist joint and its gripper
    c = client(srv.url + "/aloha/act", chunk_length=50, action_indices=cols, proprio_dim=14,
               send_image_size=224, image_size=64)
    out = c.predict(make_obs(2), "fold the towel")
    assert out.actions.shape == (50, 5) and c.chunk_length == 50
    np.testing.assert_array_equal(out.actions, ALOHA_ACTIONS[:, list(cols)])
    for cam, name in (("front", "future_image"), ("side", "future_wrist_image"), ("wrist", "future_wrist_image2")):
        assert out.images[cam].shape == (64, 64, 3)  # (1, 224, 224, 3) -> batch axis dropped -> resized
        np.testing.assert_array_equal(out.images[cam], resize_image(ALOHA_IMAGES[name][0], 64))
    assert out.value == pytest.approx(0.8)
    req = protocol.decode_request(seen["aloha"])
    assert req.proprio.shape == (14,) and req.images["primary_image"].shape == (224, 224, 3)
    np.testing.assert_array_equal(req.proprio[:10], make_obs(2).proprio)
    assert req.task_description == "fold the towel"
    # run open loop, the policy queries the server once per 50-step chunk
    policy = WAMPolicy(c, "fold the towel")
    executed = [policy.act(make_obs(t, images=policy.wants_images(t))) for t in range(60)]
    assert policy.info()["query_steps"] == [0, 50]
    np.testing.assert_array_equal(np.stack(executed[:50]), ALOHA_ACTIONS[:, list(cols)])
    # left at the default 16-step chunks, the client says what to pass
    with pytest.raises(WAMServerError, match="returned 50-step chunks.*--wam-chunk-length 50"):
        client(srv.url + "/aloha/act").predict(make_obs(), "t")


def test_robocasa_shaped_answer_mapped_by_the_client(fake):
    srv, seen = fake
    c = client(srv.url + "/robocasa/act", chunk_length=32, proprio_dim=9,
               response_fields=("front=future_image", "side=future_image2", "wrist=future_wrist_image"))
    out = c.predict(make_obs(4), "t")
    np.testing.assert_array_equal(out.actions, ROBOCASA_ACTIONS[:, :5])  # dx dy dz, then two more columns
    for cam, name in (("front", "future_image"), ("side", "future_image2"), ("wrist", "future_wrist_image")):
        np.testing.assert_array_equal(out.images[cam], ROBOCASA_IMAGES[name])  # 224 px kept: no image_size
    assert out.value == pytest.approx(0.3)
    np.testing.assert_array_equal(protocol.decode_request(seen["robocasa"]).proprio, make_obs(4).proprio[:9])
    # the default mapping asks for future_wrist_image2, which a RoboCasa model does not predict
    with pytest.raises(WAMServerError, match="no 'future_wrist_image2' image"):
        client(srv.url + "/robocasa/act", chunk_length=32).predict(make_obs(), "t")


def test_cosmos_robocasa_profile_maps_a_robocasa_shaped_server(fake):
    srv, seen = fake
    c = CosmosPolicyClient(profile="cosmos-robocasa", url=srv.url + "/wamplan-robocasa/act")
    out = c.predict(make_obs(5), "insert")
    np.testing.assert_array_equal(out.actions, ROBOCASA_ACTIONS[:16, :5])
    for cam, name in (("front", "future_image"), ("side", "future_image2"), ("wrist", "future_wrist_image")):
        np.testing.assert_array_equal(out.images[cam], ROBOCASA_IMAGES[name])
    assert out.value == pytest.approx(0.6) and c.chunk_length == 16
    req = protocol.decode_request(seen["wamplan-robocasa"], protocol.ROBOCASA_REQUEST_IMAGE_FIELDS)
    assert set(json_numpy.loads(seen["wamplan-robocasa"])) == {*protocol.ROBOCASA_REQUEST_IMAGE_FIELDS, "proprio",
                                                               "task_description"}
    for cam, name in (("front", "primary_image"), ("side", "secondary_image"), ("wrist", "wrist_image")):
        np.testing.assert_array_equal(req.images[name], resize_image(make_obs(5).images[cam], 224))
    np.testing.assert_array_equal(req.proprio, make_obs(5).proprio)  # 10-D, as exported
    # an option given beside the profile wins over the profile's value
    c = CosmosPolicyClient(profile="cosmos-robocasa", url=srv.url + "/robocasa/act", chunk_length=32)
    np.testing.assert_array_equal(c.predict(make_obs(), "t").actions, ROBOCASA_ACTIONS[:, :5])


def test_cosmos_aloha_profile_maps_an_aloha_shaped_server(fake):
    srv, seen = fake
    c = CosmosPolicyClient(profile="cosmos-aloha", url=srv.url + "/aloha/act")
    out = c.predict(make_obs(3), "fold")
    assert out.actions.shape == (50, 5) and out.value == pytest.approx(0.8)
    np.testing.assert_array_equal(out.actions, ALOHA_ACTIONS[:, :5])
    for cam, name in (("front", "future_image"), ("side", "future_wrist_image"), ("wrist", "future_wrist_image2")):
        np.testing.assert_array_equal(out.images[cam], ALOHA_IMAGES[name][0])
    req = protocol.decode_request(seen["aloha"])
    assert req.proprio.shape == (14,) and req.images["left_wrist_image"].shape == (224, 224, 3)
    np.testing.assert_array_equal(req.proprio, np.r_[make_obs(3).proprio, np.zeros(4, np.float32)])


def test_our_server_with_robocasa_fields_serves_the_profile():
    wam = EchoWAM()
    rmap = {"primary_image": "front", "secondary_image": "side", "wrist_image": "wrist"}
    resp = {"front": "future_image", "side": "future_image2", "wrist": "future_wrist_image"}
    with BackgroundServer(create_app(wam, request_map=rmap, response_map=resp)) as srv:
        c = CosmosPolicyClient(profile="cosmos-robocasa", url=srv.url + "/act")
        obs = make_obs(7)
        out = c.predict(obs, "t")
    np.testing.assert_allclose(out.actions, CHUNK + 0.01, atol=1e-6)
    for cam in CAMERAS:  # the echo inverts what it was sent: the 224 px view of each camera
        np.testing.assert_array_equal(out.images[cam], 255 - resize_image(obs.images[cam], 224))


def test_profiles_are_valid_and_unknown_ones_are_named():
    for name in PROFILES:
        assert profile_config(name, url="http://h:1/act").url == "http://h:1/act"
    with pytest.raises(ConfigError, match="unknown profile 'cosmos-libero'.*cosmos-aloha"):
        profile_config("cosmos-libero")
    with pytest.raises(ConfigError, match="exactly once"):  # the two field sets cannot be mixed
        CosmosClientConfig(request_fields=("front=primary_image", "side=secondary_image", "wrist=right_wrist_image"))


def test_empty_instruction_uses_server_default(echo):
    srv, wam = echo
    client(srv.url + protocol.ROUTE).predict(make_obs(), "")
    assert wam.calls[-1][1] == "default task"


def test_request_follows_cosmos_field_names(fake):
    srv, seen = fake
    obs = make_obs(3)
    client(srv.url + "/record/act").predict(obs, "task A")
    raw = json.loads(seen["record"])  # plain JSON: arrays are json_numpy dicts
    assert set(raw) == {"primary_image", "left_wrist_image", "right_wrist_image", "proprio", "task_description"}
    assert raw["primary_image"]["dtype"] == "|u1" and "__numpy__" in raw["primary_image"]
    req = protocol.decode_request(seen["record"])
    np.testing.assert_array_equal(req.images["primary_image"], obs.images["front"])
    np.testing.assert_array_equal(req.images["left_wrist_image"], obs.images["side"])
    np.testing.assert_array_equal(req.images["right_wrist_image"], obs.images["wrist"])
    assert req.proprio.dtype == np.float32 and req.task_description == "task A"


def test_custom_camera_mapping(echo):
    srv, _ = echo
    obs = make_obs(5)
    c = client(srv.url + protocol.ROUTE,
               request_fields=("side=primary_image", "front=left_wrist_image", "wrist=right_wrist_image"),
               response_fields=("front=future_wrist_image", "wrist=future_image"))
    out = c.predict(obs, "t")
    assert c.cameras == ("front", "wrist") and set(out.images) == {"front", "wrist"}
    # server: primary_image -> its 'front' = our side, left_wrist_image -> its 'side' = our front
    np.testing.assert_array_equal(out.images["front"], 255 - obs.images["front"])  # via future_wrist_image
    np.testing.assert_array_equal(out.images["wrist"], 255 - obs.images["side"])  # via future_image


def test_action_proprio_and_image_adaptation(fake):
    srv, seen = fake
    c = client(srv.url + "/record/act", action_indices=(0, 2, 4, 5, 6), proprio_dim=12, proprio_pad=-1.0,
               image_size=16, send_image_size=20)
    out = c.predict(make_obs(), "t")
    served = np.linspace(-0.5, 0.5, H * 7, dtype=np.float32).reshape(H, 7)
    np.testing.assert_array_equal(out.actions, served[:, [0, 2, 4, 5, 6]])
    assert all(img.shape == (16, 16, 3) and img.dtype == np.uint8 for img in out.images.values())
    req = protocol.decode_request(seen["record"])
    np.testing.assert_array_equal(req.proprio, np.r_[np.arange(10) / 10, -1, -1].astype(np.float32))
    assert req.images["primary_image"].shape == (20, 20, 3)
    client(srv.url + "/record/act", proprio_dim=4).predict(make_obs(), "t")
    proprio = protocol.decode_request(seen["record"]).proprio  # (4,)
    np.testing.assert_array_equal(proprio, np.arange(4, dtype=np.float32) / 10)


def test_double_encoded_answer_is_accepted(fake):
    srv, _ = fake
    out = client(srv.url + "/double/act").predict(make_obs(), "t")
    assert out.actions.shape == (H, A) and out.value == pytest.approx(0.5)


def test_actions_are_clipped_or_rejected(fake):
    srv, _ = fake
    out = client(srv.url + "/overshoot/act").predict(make_obs(), "t")
    assert out.actions.max() == 1.0
    with pytest.raises(WAMServerError, match=r"outside \[-1, 1\]"):
        client(srv.url + "/overshoot/act", clip_actions=False).predict(make_obs(), "t")


# -- failures -------------------------------------------------------------------------------------------
def test_server_down_is_a_clear_error():
    url = f"http://127.0.0.1:{free_port()}/act"
    with pytest.raises(WAMServerError, match=r"not reachable \(connection refused.*--wam-url") as e:
        client(url, retries=1).predict(make_obs(), "t")
    assert url in str(e.value) and "\n" not in str(e.value)


def test_a_failing_wam_is_reported_with_its_reason(failing):
    """Our server says why it failed (HTTP 500 and the WAM's error); with --bare-errors it answers as Cosmos
    Policy's does, HTTP 200 and "error", which the client reports too."""
    with pytest.raises(WAMServerError, match=r"answered HTTP 500 \(the WAM 'test-echo' failed on this request "
                                             r"\(RuntimeError: the model blew up\); the server's log has the traceback"):
        client(failing.url + protocol.ROUTE).predict(make_obs(), "t")
    with BackgroundServer(create_app(EchoWAM(fail=True), bare_errors=True)) as srv:
        with pytest.raises(WAMServerError, match=r'answered "error".*traceback'):
            client(srv.url + protocol.ROUTE).predict(make_obs(), "t")


def test_error_reply_from_fake_server(fake):
    srv, _ = fake
    with pytest.raises(WAMServerError, match=r'answered "error"'):
        client(srv.url + "/error/act").predict(make_obs(), "t")


def test_server_answers_a_malformed_request_with_its_reason(echo):
    srv, _ = echo
    body = json_numpy.dumps({"primary_image": np.zeros((4, 4, 3), np.uint8), "proprio": np.zeros(10, np.float32),
                             "task_description": "t"})  # both wrist images missing
    r = requests.post(srv.url + protocol.ROUTE, data=body, headers=protocol.JSON_HEADERS, timeout=10)
    assert r.status_code == 400
    assert r.json() == {"error": "bad /act request: the request lacks field(s) ['left_wrist_image', "
                                 "'right_wrist_image']"}
    assert requests.get(srv.url + "/health", timeout=10).json()["ok"] is True  # ours adds one (issue 17)
    with BackgroundServer(create_app(EchoWAM(), bare_errors=True)) as bare:  # as Cosmos Policy's deploy.py
        r = requests.post(bare.url + protocol.ROUTE, data=body, headers=protocol.JSON_HEADERS, timeout=10)
        assert r.status_code == 200 and r.json() == "error"


@pytest.mark.parametrize("case", sorted(BAD_ANSWERS))
def test_malformed_answers_are_clear_errors(fake, case):
    srv, _ = fake
    with pytest.raises(WAMServerError) as e:
        client(srv.url + f"/{case}/act").predict(make_obs(), "t")
    msg = str(e.value)
    assert BAD_ANSWERS[case][1] in msg and "Cosmos Policy server at" in msg and "\n" not in msg


def test_http_errors_are_clear(fake):
    srv, _ = fake
    with pytest.raises(WAMServerError, match="answered HTTP 500"):
        client(srv.url + "/http500/act").predict(make_obs(), "t")
    with pytest.raises(WAMServerError, match=r"HTTP 404.*--wam-url"):
        client(srv.url + "/act/does/not/exist").predict(make_obs(), "t")


@pytest.mark.timeout(20)
def test_timeout_is_a_clear_error_and_not_retried(fake):
    srv, seen = fake
    c = client(srv.url + "/slow/act", timeout_s=0.3, retries=3)
    with pytest.raises(WAMServerError, match=r"did not answer within 0.3 s.*--wam-timeout-s"):
        c.predict(make_obs(), "t")
    assert c.attempts_made == 1


class FlakySession:
    """Fails the first ``failures`` posts with a connection error, then delegates to a real session."""

    def __init__(self, failures: int):
        self.failures, self.calls, self.real = failures, 0, requests.Session()

    def post(self, *args, **kwargs):
        self.calls += 1
        if self.calls <= self.failures:
            raise requests.exceptions.ConnectionError("[Errno 111] Connection refused")
        return self.real.post(*args, **kwargs)

    def close(self):
        self.real.close()


def test_retries_are_bounded():
    session = FlakySession(failures=100)
    c = CosmosPolicyClient(CosmosClientConfig(retries=2, backoff_s=0.0), session=session)
    with pytest.raises(WAMServerError, match=r"connection refused, 3 attempt\(s\)"):
        c.predict(make_obs(), "t")
    assert session.calls == 3


def test_retry_recovers_from_a_transient_failure(echo):
    srv, _ = echo
    session = FlakySession(failures=1)
    c = CosmosPolicyClient(CosmosClientConfig(url=srv.url + protocol.ROUTE, retries=2, backoff_s=0.0), session=session)
    out = c.predict(make_obs(), "t")
    assert session.calls == 2 and out.extras["attempts"] == 2


@pytest.mark.parametrize("kw, match", [
    (dict(url="127.0.0.1:8777/act"), "http"),
    (dict(request_fields=("front=primary_image", "side=left_wrist_image")), "exactly once"),
    (dict(request_fields=("top=primary_image", "side=left_wrist_image", "wrist=right_wrist_image")),
     "unknown camera"),
    (dict(response_fields=("front=future_picture",)), "unknown field"),
    (dict(response_fields=("front=future_image", "front=future_wrist_image")), "camera twice"),
    (dict(action_indices=(0, 0, 1)), "distinct"),
    (dict(timeout_s=0.0), "> 0"),
    (dict(retries=-1), "retries"),
])
def test_client_config_is_validated(kw, match):
    with pytest.raises(ConfigError, match=match):
        CosmosClientConfig(**kw)


def test_client_maps_the_cameras_of_its_task():
    c = CosmosPolicyClient(CosmosClientConfig())
    assert c.task.name == "cube-insertion" and c.cameras == CAMERAS and c.action_dim == 5
    fields = dict(request_fields=("base_camera=primary_image", "hand_camera=left_wrist_image",
                                  "hand_camera=right_wrist_image"),
                  response_fields=("base_camera=future_image", "hand_camera=future_wrist_image"),
                  action_indices=tuple(range(7)))
    peg = CosmosPolicyClient(CosmosClientConfig(task="peg-insertion-side", **fields))
    assert peg.task.name == "peg-insertion-side" and peg.cameras == ("base_camera", "hand_camera")
    assert peg.action_dim == 7 and peg.default_instruction == peg.task.instruction
    by_position = CosmosPolicyClient(CosmosClientConfig(task="peg-insertion-side"))  # unset: the task's own
    assert by_position.config.request_map == peg.config.request_map
    assert by_position.config.response_map == peg.config.response_map and by_position.action_dim == 7
    with pytest.raises(ConfigError, match=r"unknown camera 'front'.*\['base_camera', 'hand_camera'\]"):
        profile_config("cosmos-robocasa", task="peg-insertion-side")  # it names the cube's cameras
    aloha = profile_config("cosmos-aloha", task="peg-insertion-side")  # ALOHA's field names, the task's cameras
    assert aloha.request_map == by_position.config.request_map and aloha.chunk_length == 50
    cube = profile_config("cosmos-aloha")  # the cube's mapping, as the profile spelled it out before
    assert cube.request_pairs == ("front=primary_image", "side=left_wrist_image", "wrist=right_wrist_image")
    assert cube.response_pairs == ("front=future_image", "side=future_wrist_image", "wrist=future_wrist_image2")
    recorded = CosmosPolicyClient(cube).config_dict()  # the record holds the mapping in use
    assert recorded["request_fields"] == list(cube.request_pairs) and recorded["action_indices"] == [0, 1, 2, 3, 4]
    with pytest.raises(ConfigError, match="unknown camera 'base_camera'"):
        CosmosClientConfig(**fields)
    with pytest.raises(UserError, match="unknown task 'no-such-task'"):
        CosmosClientConfig(task="no-such-task")


def test_client_flags_take_lists_and_unset_ones_follow_the_task():
    """``tuple[...] | None`` fields become list flags (``--wam-action-indices 0 1 ...``); unset, they follow the
    task: its action size and its cameras by position."""
    import argparse

    from wamplan.config import add_arguments, from_args
    from wamplan.envs.spec import get_task

    parser = argparse.ArgumentParser()
    add_arguments(parser, CosmosClientConfig, prefix="wam_")
    args = parser.parse_args(["--wam-task", "peg-insertion-side", "--wam-action-indices", "6", "0", "1",
                              "--wam-response-fields", "hand_camera=future_image"])
    cfg = from_args(CosmosClientConfig, args, prefix="wam_")
    assert cfg.action_columns == (6, 0, 1) and cfg.response_map == {"hand_camera": "future_image"}
    assert cfg.request_map["primary_image"] == "base_camera"
    push = CosmosClientConfig(task="push-cube")  # one camera fills all three request images
    assert set(push.request_map.values()) == {"base_camera"} and push.response_map == {"base_camera": "future_image"}
    assert push.action_columns == tuple(range(get_task("push-cube").action_dim))
    assert CosmosClientConfig().action_columns == (0, 1, 2, 3, 4)


def test_server_maps_other_cameras_by_position():
    from wamplan.wam.protocol import DEFAULT_REQUEST_MAP, DEFAULT_RESPONSE_MAP, default_maps

    assert default_maps(CAMERAS) == (DEFAULT_REQUEST_MAP, DEFAULT_RESPONSE_MAP)
    request, response = default_maps(("base_camera", "hand_camera"))
    assert request == {"primary_image": "base_camera", "left_wrist_image": "hand_camera",
                       "right_wrist_image": "hand_camera"}
    assert response == {"base_camera": "future_image", "hand_camera": "future_wrist_image"}
    request, response = default_maps(("front", "wrist"))  # a subset of the cube's names maps by position too
    assert set(request.values()) == {"front", "wrist"} and response == {"front": "future_image",
                                                                        "wrist": "future_wrist_image"}


def test_a_wam_that_names_no_task_acts_in_the_cube_task():
    wam = EchoWAM()
    assert wam.task.name == "cube-insertion" and wam.cameras == CAMERAS and wam.action_dim == 5
    assert wam.default_instruction == DEFAULT_INSTRUCTION == wam.task.instruction
    wam.task = "push-cube"
    assert wam.cameras == ("base_camera",) and wam.action_dim == 7
    with pytest.raises(WAMError, match="outputs 5-D actions but task push-cube takes 7-D"):
        wam.action_dim = 5
        WAMPolicy(wam, "push", task="push-cube")


def test_make_wam_builds_the_client():
    c = make_wam("cosmos", url="http://127.0.0.1:9/act", chunk_length=8)
    assert isinstance(c, CosmosPolicyClient) and c.chunk_length == 8 and c.config.url.endswith(":9/act")
    with pytest.raises(WAMError, match="unknown WAM"):
        make_wam("no-such-wam")
    with pytest.raises(ConfigError, match="unknown option"):
        make_wam("cosmos", ulr="x")


# -- protocol unit --------------------------------------------------------------------------------------
def test_protocol_round_trips_and_double_encoding():
    obs = make_obs()
    req = protocol.ActRequest(images={"primary_image": obs.images["front"], "left_wrist_image": obs.images["side"],
                                      "right_wrist_image": obs.images["wrist"]},
                              proprio=obs.proprio, task_description="x")
    body = protocol.encode_request(req)
    for form in (body, json.dumps({"encoded": body})):
        back = protocol.decode_request(form)
        for k in protocol.REQUEST_IMAGE_FIELDS:
            np.testing.assert_array_equal(back.images[k], req.images[k])
        assert back.images["primary_image"].flags.writeable
    resp = protocol.ActResponse(actions=CHUNK, future_images={"future_image": obs.images["front"]}, value=None)
    ans = protocol.decode_response(protocol.encode_response(resp))
    np.testing.assert_array_equal(ans.actions, CHUNK)
    assert set(ans.future_images) == {"future_image"} and ans.value is None
    with pytest.raises(protocol.ErrorReply):
        protocol.decode_response(error_reply())


# -- validation -----------------------------------------------------------------------------------------
def _out(**changes) -> WAMOutput:
    img = np.zeros((8, 8, 3), np.uint8)
    kw = dict(actions=CHUNK.copy(), images={c: img for c in CAMERAS}, value=0.1)
    kw.update(changes)
    return WAMOutput(**kw)


@pytest.mark.parametrize("changes, match", [
    (dict(actions=np.zeros((15, 5), np.float32)), "shape"),
    (dict(actions=np.zeros((16, 5), np.float64)), "float32"),
    (dict(actions=np.full((16, 5), np.nan, np.float32)), "non-finite"),
    (dict(actions=np.full((16, 5), 1.5, np.float32)), r"outside \[-1, 1\]"),
    (dict(images={"front": np.zeros((8, 8, 3), np.uint8)}), "no image for camera"),
    (dict(images={c: np.zeros((8, 8, 3), np.float32) for c in CAMERAS}), "uint8"),
    (dict(images={c: np.zeros((8, 8), np.uint8) for c in CAMERAS}), r"\(h, w, 3\)"),
    (dict(value=float("nan")), "value"),
])
def test_validation_rejects_broken_outputs(changes, match):
    with pytest.raises(WAMOutputError, match=match):
        validate_wam_output(_out(**changes), chunk_length=H, action_dim=A, cameras=CAMERAS)


def test_validation_accepts_a_good_output():
    out = _out()
    assert validate_wam_output(out, chunk_length=H, action_dim=A, cameras=CAMERAS) is out


# -- WAMPolicy ------------------------------------------------------------------------------------------
def test_wam_policy_runs_chunks_open_loop_and_requeries_every_H_steps():
    wam = EchoWAM()
    policy = WAMPolicy(wam, "insert")
    policy.reset(seed=0)
    assert wam.resets == 2  # once in __init__, once here
    steps = 40
    actions = []
    for t in range(steps):
        assert policy.wants_images(t) == (t % H == 0)
        actions.append(policy.act(make_obs(t, images=policy.wants_images(t))))
    assert [o.step for o, _ in wam.calls] == [0, 16, 32]
    for k, t0 in enumerate((0, 16, 32)):
        expected = (CHUNK + 0.01 * (k + 1)).astype(np.float32)  # the k-th query's chunk
        np.testing.assert_array_equal(np.stack(actions[t0:t0 + H]), expected[: steps - t0])
    info = policy.info()
    assert info["chunks"] == 3 and info["query_steps"] == [0, 16, 32] and len(info["wam_query_s"]) == 3
    assert policy.last_output is not None and policy.last_output.value == pytest.approx(0.25)
    assert all(a.dtype == np.float32 and a.shape == (A,) for a in actions)


def test_wam_policy_defaults_to_the_wams_instruction():
    wam = EchoWAM()
    WAMPolicy(wam).act(make_obs(0))
    assert wam.calls[-1][1] == wam.default_instruction == DEFAULT_INSTRUCTION
    WAMPolicy(wam, "other task").act(make_obs(0))
    assert wam.calls[-1][1] == "other task"


def test_wam_policy_needs_images_at_chunk_boundaries():
    policy = WAMPolicy(EchoWAM(), "insert")
    with pytest.raises(WAMError, match="wants_images"):
        policy.act(make_obs(0, images=False))


def test_wam_policy_refine_hook_replaces_the_chunk_and_clips():
    wam = EchoWAM()
    policy = WAMPolicy(wam, "insert", refine=lambda obs, out: out.actions * 0 + 2.0)
    a = policy.act(make_obs(0))
    np.testing.assert_array_equal(a, np.ones(A, np.float32))
    np.testing.assert_array_equal(policy.last_output.actions, (CHUNK + 0.01).astype(np.float32))  # proposal kept
    assert len(policy.info()["refine_s"]) == 1


def test_wam_policy_rejects_a_broken_wam():
    class NaNWAM(EchoWAM):
        def predict(self, obs, instruction):
            out = super().predict(obs, instruction)
            out.actions[3, 1] = np.nan
            return out

    with pytest.raises(WAMOutputError, match="non-finite"):
        WAMPolicy(NaNWAM(), "insert").act(make_obs(0))


# -- checkpoints and CLI --------------------------------------------------------------------------------
def _fake_checkpoint(path, kind: str):
    path.mkdir()
    (path / "config.json").write_text(json.dumps({"kind": kind, "config": {}}))
    (path / "model.safetensors").write_bytes(b"")
    return path


def test_load_wam_dispatches_on_kind_and_rejects_others(tmp_path):
    with pytest.raises(CheckpointError, match="not a wamplan checkpoint"):
        load_wam(tmp_path / "nothing")
    with pytest.raises(CheckpointError, match="'world_model' checkpoint, which is not a WAM"):
        load_wam(_fake_checkpoint(tmp_path / "wm", "world_model"))

    @register_wam_loader("test-echo-wam")
    def _load(path, device="auto"):
        return EchoWAM(value=0.75)

    wam = load_wam(_fake_checkpoint(tmp_path / "echo", "test-echo-wam"))
    assert isinstance(wam, EchoWAM) and wam.value == 0.75


def test_cli_serve_rejects_a_non_wam_path(tmp_path, capsys):
    from wamplan.cli import main

    assert main(["wam", "serve", "--ckpt", str(tmp_path / "missing"), "--port", "8777"]) == 2
    err = capsys.readouterr().err
    assert "not a wamplan checkpoint" in err and err.count("\n") == 1
