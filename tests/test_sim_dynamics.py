"""The simulator oracle's fast candidate rollout (``TaskEnv.simulate``) against the full step path.

PhysX keeps hidden state from the previous rollout, which no restore clears, so two
rollouts are compared only after the same predecessor: each is preceded by a warm-up run of the same
candidate.
"""

import numpy as np
import pytest
import torch

from wamplan.encoders import make_encoder
from wamplan.envs.config import EnvConfig
from wamplan.envs.core import TaskEnv
from wamplan.planning.dynamics import SimulatorDynamics
from wamplan.envs.contract import CAMERAS
from wamplan.policies.expert import ExpertPolicy


@pytest.fixture(scope="module")
def env():
    e = TaskEnv(EnvConfig(camera_size=64))
    yield e
    e.close()


def _terminal(env) -> np.ndarray:
    s = env.privileged_state()
    return np.concatenate([env.sim_state(), s["tcp_pose"], s["cube_pose"]])  # (S + 14,)


def _full(env, snap, cand, restores: int = 1) -> np.ndarray:
    for _ in range(restores):
        env.restore(snap)
    for a in cand:
        env.step(a)
    return _terminal(env)


def _boundary(env, seed: int, steps: int, n: int = 3):
    """Drive the expert ``steps`` steps; return the snapshot and n candidates: its next chunk, then noisy copies."""
    env.reset(seed)
    expert, obs = ExpertPolicy(), env.observe()
    expert.reset()
    chunk = []
    for t in range(steps + 16):
        if t == steps:
            snap = env.snapshot()
        a = env.check_action(expert.act(obs))
        chunk.append(a)
        obs, _ = env.step(a)
    chunk = np.stack(chunk[steps:])  # (16, 5)
    rng = np.random.default_rng(seed)
    noisy = [np.clip(chunk + rng.normal(0, 0.3, chunk.shape), -1, 1) for _ in range(n - 1)]
    return snap, np.stack([chunk, *noisy]).astype(np.float32)  # (n, 16, 5)


# grasped, carrying: the cube in the fingers at the boundary (the approach before it, nothing touched, is the easier
# case); at each, the expert's next chunk and one noisy copy of it
@pytest.mark.parametrize("seed,steps", [(1, 48), (7, 96)])
def test_simulate_reaches_the_full_steps_terminal_state_bit_for_bit(env, seed, steps):
    snap, cands = _boundary(env, seed, steps, n=2)
    for cand in cands:
        _full(env, snap, cand)  # warm-up: both rollouts below follow this candidate's end
        views = env.simulate(snap, cand[None])  # (1, V, H, W, 3)
        fast = _terminal(env)
        full = _full(env, snap, cand)
        np.testing.assert_array_equal(fast, full)
        np.testing.assert_array_equal(views[0], np.stack([env.render(cull=False)[c] for c in CAMERAS]))
        np.testing.assert_array_equal(_full(env, snap, cand, restores=2), full)  # twice is as exact as once
    assert np.abs(_terminal(env) - _full(env, snap, cands[0])).max() > 1e-3  # the candidates differ


def test_simulator_dynamics_leaves_the_env_at_the_snapshot(env):
    snap, cands = _boundary(env, 1, 40)
    env.restore(snap)
    start = _terminal(env)
    proprio = env.proprio()
    exact = (env.drive_targets(), env.step_count, dict(env.reached), env.outcome())
    dyn = SimulatorDynamics(env, make_encoder("patch-pixels", input_size=32, patch_size=16, proj_dim=16))
    dyn.prepare(None)
    z = dyn.terminal(torch.from_numpy(cands))
    assert z.shape == (3, len(CAMERAS), 4, 16)
    # The fixed robot base's pose reads back with ~1e-8 m of float noise that depends on the previous rollout
    # (1.5e-10 against 2.2e-10 here), and the TCP pose in the proprio is read through it (one float32 ulp, 6e-8 m,
    # seen on one machine); everything else is exact.
    np.testing.assert_allclose(_terminal(env), start, rtol=0, atol=1e-7)
    np.testing.assert_allclose(env.proprio(), proprio, rtol=0, atol=1e-7)
    for x, y in zip(exact, (env.drive_targets(), env.step_count, dict(env.reached), env.outcome())):
        np.testing.assert_array_equal(x, y)
    assert snap.step == env.step_count == 40 and env.observe().step == 40


def test_culled_render_is_pixel_identical(env):
    env.reset(0)
    expert, obs = ExpertPolicy(), env.observe()
    expert.reset()
    culled = []
    for t in range(100):
        obs, _ = env.step(env.check_action(expert.act(obs)))
        if t % 33 == 0:
            cams = {c: env.base.scene.sensors[c].camera._render_cameras[0] for c in CAMERAS}
            culled.append(len(env._outside_frustum(cams["wrist"])))
            plain, fast = env.render(cull=False), env.render()  # culling is render's default
            for c in CAMERAS:
                np.testing.assert_array_equal(plain[c], fast[c])
    assert min(culled) >= 5  # the wrist camera sees little of the arm: culling is exercised
    assert all(b.visibility == 1.0 for b in env._bodies[1])  # and every body is shown again


def test_culling_follows_the_scene_a_reset_rebuilds(env, monkeypatch):
    """A reset after steps rebuilds the scene (new bodies); a render then still hides, while its camera draws, the
    new scene's bodies outside that camera's view, and shows them all again afterwards."""
    import sapien

    seen: list[int] = []
    for seed in (0, 1):
        env.reset(seed)
        env.step(np.zeros(5, np.float32))  # physics stepped: the next reset rebuilds the scene
        before = env.base.scene.sub_scenes[0]
        env.reset(seed)
        scene = env.base.scene.sub_scenes[0]
        assert scene is not before
        bodies = [c for c in (e.find_component_by_type(sapien.render.RenderBodyComponent) for e in scene.entities)
                  if c is not None]  # (the rebuilt scene's render bodies)
        wrist = env.base.scene.sensors["wrist"]
        capture = wrist.capture
        monkeypatch.setattr(wrist, "capture", lambda: (seen.append(sum(c.visibility == 0.0 for c in bodies)),
                                                       capture()))
        env.render(("wrist",))
        monkeypatch.undo()
        assert all(c.visibility == 1.0 for c in bodies)
    assert min(seen) >= 5  # the wrist camera sees little of the arm: its links are hidden while it draws


def test_simulate_guards_the_stale_env(env):
    env.reset(2)
    snap = env.snapshot()
    env.simulate(snap, np.zeros((1, 4, 5), np.float32), cameras=("front",))
    with pytest.raises(RuntimeError, match="restore"):
        env.step(np.zeros(5, np.float32))
    with pytest.raises(RuntimeError, match="restore"):
        env.observe()
    env.restore(snap)
    env.step(np.zeros(5, np.float32))
    with pytest.raises(ValueError, match=r"\(B, L, 5\)"):
        env.simulate(snap, np.zeros((4, 5), np.float32))
    with pytest.raises(ValueError, match="finite"):
        env.simulate(snap, np.full((1, 4, 5), np.nan, np.float32))


def test_blended_dynamics_moves_the_models_prediction_toward_the_simulators(env):
    """BlendedDynamics (the --oracle-blend diagnostic) is the model at weight 0, the simulator at 1, and the
    straight line between them in embedding space at any other weight; the env is left at the snapshot."""
    from wamplan.planning.dynamics import BlendedDynamics, LearnedDynamics, PlanningContext
    from wamplan.worldmodel.load import load_world_model

    model, enc = load_world_model("checkpoints/mini/wm_augmented")
    learned, sim = LearnedDynamics(model), SimulatorDynamics(env, enc)
    snap, cands = _boundary(env, 1, 48)
    env.restore(snap)
    views = env.render()
    z_now = enc.encode(np.stack([views[c] for c in CAMERAS]))  # (V, N, D) the boundary's frame
    q_now = torch.as_tensor(env.proprio(), dtype=torch.float32)  # (P,)
    tc, fs = learned.context, learned.frameskip
    hold = torch.zeros(fs, 5)
    hold[:, 4] = 1.0
    context = PlanningContext(z_now.expand(tc, *z_now.shape).clone(), q_now.expand(tc, -1).clone(),
                              hold.reshape(1, -1).expand(tc - 1, -1).clone())  # a resting history
    acts = torch.from_numpy(cands)  # (3, 16, 5)
    learned.prepare(context)
    sim.prepare(context)
    z_model, z_sim = learned.terminal(acts).float(), sim.terminal(acts).float()  # (3, V, N, D)
    assert (z_model - z_sim).abs().max() > 0.5  # the model errs: there is something to blend
    for w, expected in ((0.0, z_model), (1.0, z_sim), (0.25, 0.75 * z_model + 0.25 * z_sim)):
        blend = BlendedDynamics(LearnedDynamics(model), SimulatorDynamics(env, enc), w)
        assert blend.needs_history and blend.covered(16) == 16
        blend.prepare(context)
        # a rollout repeats the simulator's only up to PhysX's hidden state (< 0.01 here, against a model error of ~2)
        torch.testing.assert_close(blend.terminal(acts), expected, atol=1e-5 + 0.02 * w, rtol=0)
        assert env.step_count == 48  # the simulator restored its snapshot
    with pytest.raises(ValueError, match="outside"):
        BlendedDynamics(learned, sim, 1.5)


def test_oracle_blend_is_checked_in_one_line():
    from wamplan.config import ConfigError
    from wamplan.errors import UserError
    from wamplan.evaluation.config import EvalConfig

    with pytest.raises(ConfigError, match="outside"):
        EvalConfig(oracle_blend=-0.1)
    cfg = EvalConfig(wam="checkpoints/mini/tinywam", oracle_blend=0.5)
    with pytest.raises(UserError, match="add condition 6 or 7"):
        cfg.check_for([1, 5])
    EvalConfig(wam="checkpoints/mini/tinywam", wm_augmented="checkpoints/mini/wm_augmented",
               oracle_blend=0.5).check_for([1, 7])
