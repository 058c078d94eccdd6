"""The API's last bare errors (issue 75, item 4): an argument of the wrong type or range is one exception that names
the argument and what it takes, raised where it is given (not deep inside, not at the first plan); a WAM handed to
``run_episode`` runs open loop."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import wamplan
from wamplan.config import ConfigError

WAM, WM = "checkpoints/mini/tinywam", "checkpoints/mini/wm_augmented"


def test_wrong_types_name_the_argument():
    from wamplan.wam.cosmos_client import CosmosPolicyClient

    with pytest.raises(TypeError, match=r"load_wam's path takes a WAM checkpoint directory \(a str or Path\), got int "
                                        r"123"):
        wamplan.load_wam(123)
    with pytest.raises(TypeError, match=r"register_task takes a TaskSpec .*got str 'pick-cube'; a registered task's "
                                        r"spec is get_task\('pick-cube'\)"):
        wamplan.register_task("pick-cube")
    assert "pick-cube" not in wamplan.tasks()
    with pytest.raises(ConfigError, match=r"\.url must be text \(a str\), got int 8777"):
        CosmosPolicyClient(url=8777)


def test_view_weights_that_do_not_fit_the_cameras_are_refused_when_the_policy_is_built():
    with pytest.raises(ConfigError, match="gives 2 weights, but task 'cube-insertion' has 3 cameras"):
        wamplan.planned_policy(WAM, WM, device="cpu", cost={"view_weights": (1, 1)})


def test_views_of_mixed_sizes_name_the_camera():
    pol = wamplan.planned_policy(WAM, WM, device="cpu")
    cams = pol.wam.task.cameras
    images = {c: np.zeros((64, 64, 3), np.uint8) for c in cams}
    obs = wamplan.Observation(step=0, proprio=np.zeros(10, np.float32), images=images)
    with pytest.raises(ValueError, match=rf"plan_chunk: the '{cams[1]}' image is 32x48 pixels but the '{cams[0]}' "
                                         rf"image is 64x64; give every camera's image the same size"):
        pol.plan_chunk(dataclasses.replace(obs, images={**images, cams[1]: np.zeros((32, 48, 3), np.uint8)}))


def test_run_episode_takes_a_policy_or_a_wam_and_a_seed(monkeypatch):
    from types import SimpleNamespace

    from wamplan import api
    from wamplan.policies import make_policy
    from wamplan.policies.rollout import run_episode
    from wamplan.wam import WAMPolicy

    env = SimpleNamespace(task=wamplan.get_task("cube-insertion"))  # refused before the env is touched
    wam = wamplan.load_wam(WAM, device="cpu")
    with pytest.raises(TypeError, match=r"run_episode's policy takes a wamplan Policy, got str 'expert'; build it "
                                        r"first: wamplan.policies.make_policy\('expert'"):
        wamplan.run_episode(env, "expert", seed=0)
    with pytest.raises(TypeError, match="got TinyWAM .*a WAM predicts chunks: run it open loop as WAMPolicy"):
        run_episode(env, wam, 0)  # the layer below the API does not wrap it: it says how
    policy = make_policy("expert", task=env.task)
    with pytest.raises(ValueError, match=r"run_episode's seed must lie in 0 .. 4294967295, got -1"):
        wamplan.run_episode(env, policy, seed=-1)
    with pytest.raises(TypeError, match=r"run_episode's seed takes an int in 0 .. 4294967295, got str '0'"):
        wamplan.run_episode(env, policy, seed="0")
    ran = []
    monkeypatch.setattr(api, "_run_episode", lambda e, p, seed, **o: ran.append((e, p, seed, o)))
    wamplan.run_episode(env, wam, seed=0, max_steps=3)  # a WAM runs open loop, as WAMPolicy runs it
    (e, p, seed, options), = ran
    assert isinstance(p, WAMPolicy) and p.wam is wam and p.task is env.task
    assert (e, seed, options) == (env, 0, {"max_steps": 3})


def test_a_logged_episode_takes_finite_actions_and_proprio():
    from wamplan.data.store import EpisodeData, StoreError

    task = wamplan.get_task("cube-insertion")
    t = 8
    actions, proprio = np.zeros((t, task.action_dim)), np.zeros((t + 1, task.proprio_dim))
    images = {c: np.zeros((3, 16, 16, 3), np.uint8) for c in task.cameras}
    assert EpisodeData.logged(task, 0, actions, proprio, images, [0, 4, 8]).length == t
    actions[2, 1] = np.nan
    proprio[5, 0] = np.inf
    with pytest.raises(StoreError, match=r"actions hold NaN or inf at step\(s\) \[2\].*proprio hold NaN or inf at "
                                         r"step\(s\) \[5\]"):
        EpisodeData.logged(task, 0, actions, proprio, images, [0, 4, 8])
