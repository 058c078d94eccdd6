"""``--history imagined`` on the planning proxy: a client that posts only at chunk boundaries, as Cosmos Policy's and
openpi's clients do unmodified (no ``chunk_frames``), gets every chunk after the first planned by the shipped Δ = 4
world model, with the actions of the same episode planned in process with ``history="imagined"``; the start-up
banner says that the in-chunk frames are imagined."""

from __future__ import annotations

import numpy as np
import pytest

from wamplan.api import planned_policy
from wamplan.planning.policy_config import PlannedPolicyConfig
from wamplan.proxy.app import create_proxy_app
from wamplan.proxy.build import build_proxy
from wamplan.proxy.config import ProxyConfig
from wamplan.serving.runner import BackgroundServer
from wamplan.wam.base import load_wam

from test_proxy import WAM_CKPT, WM_CKPT, H, observation  # noqa: I001

pytestmark = pytest.mark.usefixtures("one_thread")
CHUNKS = 3


@pytest.fixture(scope="module")
def proxy():
    from test_proxy_openpi import WS_FIELDS

    p = build_proxy(ProxyConfig(upstream=WAM_CKPT, world_model=WM_CKPT, device="cpu", errors="http",
                                ws_fields=WS_FIELDS, fit_proprio=True),
                    planning={"policy": PlannedPolicyConfig(history="imagined")})
    with BackgroundServer(create_proxy_app(p)) as srv:
        yield srv, p
    p.close()


def imagined_in_process(client: int) -> np.ndarray:
    """The episode of ``observation(client, .)`` planned in process with an imagined history -> (CHUNKS x H, A)."""
    policy = planned_policy(load_wam(WAM_CKPT, device="cpu"), world_model=WM_CKPT, device="cpu", history="imagined")
    policy.reset(seed=0)
    acts = [policy.act(observation(client, t, policy.wants_images(t))) for t in range(CHUNKS * H)]
    assert [c["planned"] for c in policy.chunks] == [False] + [True] * (CHUNKS - 1)
    return np.stack(acts)


def test_openpis_unmodified_client_is_planned_from_the_boundaries(proxy):
    pytest.importorskip("openpi_client", reason="openpi's client is installed by scripts/setup.sh (make test)")
    from openpi_client.websocket_client_policy import WebsocketClientPolicy
    from test_proxy_openpi import aloha

    srv, _ = proxy
    client = WebsocketClientPolicy(host=f"ws://{srv.host}:{srv.port}/s/arm")
    answers = [client.infer(aloha(6, k * H)) for k in range(CHUNKS)]  # what its robot loop sends: observations only
    assert [a["wamplan"]["open_loop"] for a in answers] == ["first-chunk"] + [None] * (CHUNKS - 1)
    np.testing.assert_allclose(np.concatenate([a["actions"] for a in answers]), imagined_in_process(6), atol=1e-6)


def test_deploy_docs_smoke_test_prints_what_it_shows(proxy, capsys):
    """docs/deploy.md's smoke test (a ```py block, then the ```text it prints) run against a proxy of the shipped
    models with the serve's default (imagined) history, as the document starts one."""
    import contextlib
    import io
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "deploy.md").read_text()
    m = re.search(r"\*\*Smoke test\.\*\*.*?```py\n(.*?)```.*?```text\n(.*?)```", text, re.DOTALL)
    assert m, "docs/deploy.md lost its smoke test (a ```py block and the ```text it prints)"
    code, shown = m.groups()
    srv, _ = proxy
    assert "http://127.0.0.1:8778" in code
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code.replace("http://127.0.0.1:8778", srv.url), "deploy.md", "exec"), {})
    assert out.getvalue() == shown


def test_clients_running_steps_off_the_frames_grid_are_refused_at_start_up_in_one_line():
    from wamplan.errors import UserError
    from wamplan.proxy.config import ProxyPolicyConfig

    with pytest.raises(UserError) as e:  # openpi's LIBERO client runs 5 steps; the shipped model's frames are 4 apart
        build_proxy(ProxyConfig(upstream=WAM_CKPT, world_model=WM_CKPT, device="cpu"),
                    planning={"policy": ProxyPolicyConfig(requery_every=5)})
    assert "\n" not in str(e.value) and ("a client that runs 5 steps of each chunk leaves none on that grid; start "
                                         "serve with --history seen") in str(e.value)


def test_a_cube_episode_through_the_proxy_takes_the_in_process_imagined_episodes_actions(proxy, small_env):
    """A CubeInsertion-v1 episode (seed 0, three chunks) whose client posts only its boundary observations (wamplan's
    Cosmos Policy client without send_chunk_frames, as upstream's runs: no seed either, so the session plans with
    episode seed 0) takes the actions of the same episode planned in process with the imagined history, every chunk
    after the first planned."""
    from wamplan.policies.rollout import run_episode
    from wamplan.wam.base import WAMPolicy
    from wamplan.wam.cosmos_client import CosmosPolicyClient

    srv, p = proxy
    assert ("history: chunk boundaries only: the world model's frames every 4 steps inside a chunk are imagined "
            "from the last boundary and the actions run since (--history imagined)") in p.describe()
    env, seed, steps = small_env, 0, CHUNKS * H
    policy = planned_policy(load_wam(WAM_CKPT, device="cpu"), world_model=WM_CKPT, device="cpu", history="imagined")
    want: list[np.ndarray] = []
    run_episode(env, policy, seed, max_steps=steps, stop_on_success=False,
                on_obs=lambda e, o, a: want.append(a) if a is not None else None)
    client = CosmosPolicyClient(url=f"{srv.url}/s/cube/act")
    driver, got = WAMPolicy(client), []
    run_episode(env, driver, seed, max_steps=steps, stop_on_success=False,
                on_obs=lambda e, o, a: got.append(a) if a is not None else None)
    client.close()
    np.testing.assert_allclose(np.stack(got), np.stack(want), atol=1e-6)
    assert driver.info()["proxy"] == {"first-chunk": 1, "planned": CHUNKS - 1}
