"""Clients that run part of each chunk before asking again, followed by the planning proxy: openpi's own client in
its LIBERO example's pattern (``replan_steps=5``) and through its ``ActionChunkBroker`` take the actions of the same
planned policy re-queried every 5 steps in process (``requery_every=5``); ``executed_actions`` of k rows move the
session's step by k (planned from the right step where k falls on the world model's grid, open loop "off-grid",
saying why, where it does not)."""

from __future__ import annotations

import numpy as np
import pytest
import requests

pytest.importorskip("openpi_client.action_chunk_broker", reason="openpi's client is installed by scripts/setup.sh")
from openpi_client.action_chunk_broker import ActionChunkBroker  # noqa: E402
from openpi_client.websocket_client_policy import WebsocketClientPolicy  # noqa: E402

from wamplan.api import planned_policy
from wamplan.errors import UserError
from wamplan.planning.policy_config import PlannedPolicyConfig
from wamplan.proxy.app import create_proxy_app
from wamplan.proxy.build import build_proxy
from wamplan.proxy.config import ProxyConfig
from wamplan.serving.runner import BackgroundServer
from wamplan.wam.base import load_wam

from test_proxy import H, WAM_CKPT, WM_CKPT, boundary_world_model, fields, observation, post, request  # noqa: I001
from test_proxy_openpi import WS_FIELDS, aloha

pytestmark = pytest.mark.usefixtures("one_thread")


def requery_reference(world_model: str, client: int, steps: int, every: int) -> np.ndarray:
    """The same planned policy in process, re-queried every ``every`` steps -> (steps, A) actions."""
    policy = planned_policy(load_wam(WAM_CKPT, device="cpu"), world_model=world_model, device="cpu",
                            requery_every=every)
    policy.reset(seed=0)
    return np.stack([policy.act(observation(client, t, policy.wants_images(t))) for t in range(steps)])


def test_openpis_client_replanning_every_5_steps_takes_the_in_process_requery_reference(tmp_path):
    """A world model whose frames are 5 steps apart: the observations a client posts every 5 steps are its history,
    so the proxy (serve --requery-every 5) plans from step 10 on without chunk_frames."""
    wm, K, c, steps = boundary_world_model(tmp_path / "wm5", frameskip=5), 5, 3, 20
    p = build_proxy(ProxyConfig(upstream=WAM_CKPT, world_model=wm, device="cpu", ws_fields=WS_FIELDS, fit_proprio=True),
                    planning=dict(policy=PlannedPolicyConfig(requery_every=K)))
    try:
        assert "one that sends none runs 5, --requery-every" in p.describe()
        with BackgroundServer(create_proxy_app(p)) as srv:
            host = f"ws://{srv.host}:{srv.port}"
            libero, plan, reports = WebsocketClientPolicy(host=host), [], []
            got = []
            for t in range(steps):  # openpi's examples/libero/main.py: run replan_steps of each chunk, then ask again
                if not plan:
                    answer = libero.infer(aloha(c, t))
                    reports.append(answer["wamplan"])
                    plan.extend(answer["actions"][:K])
                got.append(plan.pop(0))
            broker = ActionChunkBroker(WebsocketClientPolicy(host=host), action_horizon=K)
            brokered = [broker.infer(aloha(c, t))["actions"] for t in range(steps)]
    finally:
        p.close()
    want = requery_reference(wm, c, steps, K)  # (20, 5)
    assert [(r["step"], r["open_loop"]) for r in reports] == [(0, "first-chunk"), (5, "warm-up"), (10, None),
                                                              (15, None)]
    np.testing.assert_allclose(np.stack(got), want, atol=1e-6)
    np.testing.assert_allclose(np.stack(brokered), want, atol=1e-6)
    whole = requery_reference(wm, c, H, 0)  # the same policy running whole chunks runs its first chunk open loop
    assert not np.allclose(whole[10:], want[10:H], atol=1e-3)


def test_executed_actions_of_k_rows_move_the_step_and_say_when_it_falls_off_the_grid():
    """The shipped world model (frames 4 apart): the robot runs 8 steps (frames at 0, 4, 8: planned at step 8, as the
    policy re-queried every 8 steps in process), then 5 (step 13, between its frames: open loop, saying why)."""
    p = build_proxy(ProxyConfig(upstream=WAM_CKPT, world_model=WM_CKPT, device="cpu", errors="http"))
    c = 5
    try:
        with BackgroundServer(create_proxy_app(p)) as srv:
            url = f"{srv.url}/s/part/act"
            first = post(url, request(observation(c, 0)))
            ran = np.stack(first["actions"])[:8]  # (8, 5)
            second = post(url, request(observation(c, 8), executed_actions=ran,
                                       chunk_frames={"4": fields(observation(c, 4))}))
            third = post(url, request(observation(c, 13), executed_actions=np.stack(second["actions"])[:5]))
            bad = requests.post(url, data=request(observation(c, 13), executed_actions=np.zeros((2, 5)),
                                                  chunk_frames={"3": fields(observation(c, 3))}), timeout=60)
    finally:
        p.close()
    assert (second["wamplan"]["step"], second["wamplan"]["open_loop"]) == (8, None)
    want = requery_reference(WM_CKPT, c, 16, 8)  # (16, 5)
    np.testing.assert_allclose(np.concatenate([ran, np.stack(second["actions"])[:8]]), want, atol=1e-6)
    report = third["wamplan"]
    assert (report["step"], report["open_loop"], report["planned"]) == (13, "off-grid", False)
    assert report["notes"][0] == ("the robot ran 5 steps of the last chunk, so this request (step 13) falls off the "
                                   "steps the world model plans from (every 4: its frames 4 apart, clients asking "
                                   "every 16); start serve with --requery-every 5 --history seen if the robot always runs "
                                   "that many")
    direct = load_wam(WAM_CKPT, device="cpu").predict(observation(c, 13), "insert the cube into the square hole")
    np.testing.assert_array_equal(np.stack(third["actions"]), direct.actions)  # the WAM's own chunk
    assert bad.status_code == 400 and "chunk_frames offset '3' is not in 1..1 (the robot ran 2 steps" in bad.text
    with pytest.raises(UserError, match="--requery-every 20 is longer than the upstream's 16-step chunk"):
        build_proxy(ProxyConfig(upstream=WAM_CKPT, world_model=WM_CKPT, device="cpu"),
                    planning=dict(policy=PlannedPolicyConfig(requery_every=20)))
