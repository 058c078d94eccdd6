"""``TaskEnv``: wamplan's wrapper around one instance of a registered task's ManiSkill env (``EnvConfig.task``;
the CPU simulator by default).

It speaks numpy and :class:`~wamplan.envs.contract.Observation`, renders cameras only on demand
(physics is cheap, a camera picture costs tens of milliseconds), tracks the furthest stage an episode reached, and
saves/restores complete snapshots, including what ManiSkill's ``get_state_dict`` leaves out
(controller targets, joint drive targets, the step counter). ``reset`` starts every episode as in a fresh
process, so an episode's record depends only on its seed and its policy.

``simulate`` is a planner's fast path (the simulator oracle): it rolls candidate chunks out from a
snapshot with the controller and physics only (ManiSkill's ``_step_action``: no per-step evaluation,
observation or reward) and renders only the final frame. Its terminal states and pictures are
bit-identical to ``restore``, ``step`` and ``render``. One restore is as exact as several: PhysX's hidden
state carries over from the previous rollout (cached contacts, we believe), and no number of
``set_state_dict`` calls clears it.

Rendering cost is dominated by shading the robot's meshes on the calling thread, whatever the resolution, so
culling bodies outside a camera's frustum is what pays, and every render culls by default (the same pixels;
profile: ``benchmarks/oracle.py --profile``; figures in docs/results.md).
"""

from __future__ import annotations

import copy
import itertools
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from wamplan.envs.adapters import adapter_class
from wamplan.envs.config import EnvConfig
from wamplan.envs.spec import Observation, TaskSpec

_CORNERS = np.array(list(itertools.product((0, 1), repeat=3)))  # (8, 3): min (0) or max (1) per axis


@dataclass
class Snapshot:
    """Everything needed to put the simulator back exactly: physics, controllers, counters."""

    sim: dict
    controllers: dict[str, dict[str, torch.Tensor]]
    drive_targets: torch.Tensor
    step: int
    reached: dict[str, bool]


def _clone(x: Any) -> Any:
    if torch.is_tensor(x):
        return x.clone()
    if isinstance(x, dict):
        return {k: _clone(v) for k, v in x.items()}
    return copy.deepcopy(x)


class TaskEnv:
    """One episode of the task ``config.task`` at a time; numpy in, numpy out. ``task`` is its spec.

    The methods that change simulator or controller state run with inference mode off, whatever the caller's
    mode: a planner that steps the env inside ``torch.inference_mode()`` would otherwise leave inference tensors
    in the controller, and the next ordinary step would fail on an in-place update.
    """

    def __init__(self, config: EnvConfig | None = None):
        import wamplan.envs.task  # noqa: F401  (registers the cube task, configures Vulkan)
        import mani_skill.envs  # noqa: F401  (registers ManiSkill's own tasks)

        self.config = config or EnvConfig()
        self.task: TaskSpec = self.config.spec
        adapter = adapter_class(self.task)
        self._gym = gym.make(self.task.env_id, obs_mode="state_dict", reward_mode="none", num_envs=1,
                             sim_backend=self.config.sim_backend, render_backend=self.config.render_backend,
                             **adapter.make_kwargs(self.task, self.config))
        self.base = self._gym.unwrapped
        self.adapter = adapter(self.task, self.base)
        self._check_action_space()
        self.step_count = 0
        self.seed: int | None = None
        self.reached = {s: False for s in self.task.stages}
        self._last: dict[str, Any] = {}
        self._mid_rollout = False  # set by simulate(): physics moved on without stage tracking
        self._bodies: tuple | None = None  # (scene, its render bodies), for frustum culling (see render)
        self._stepped = False  # physics stepped since the scene was built: reset rebuilds it (see reset)

    # ------------------------------------------------------------------ episode
    @torch.inference_mode(False)
    def reset(self, seed: int, with_images: bool = False) -> Observation:
        """Start the episode of ``seed``, as a fresh process would: its outcome depends only on the seed and the
        policy, never on what ran before. Once physics has stepped, the scene is rebuilt (ManiSkill's
        reconfigure, ~0.2 s): resetting poses, controllers and drive targets is not enough, as PhysX keeps
        hidden solver state across ``reset`` (an episode run after others could run differently; docs/results.md)."""
        self.seed = int(seed)
        self.base.reset(seed=self.seed, options=dict(reconfigure=self._stepped))
        self._stepped = False
        self._mid_rollout = False
        self.step_count = 0
        self.reached = {s: False for s in self.task.stages}
        self._last = self._evaluate()
        return self.observe(with_images)

    @torch.inference_mode(False)
    def step(self, action: np.ndarray, with_images: bool = False) -> tuple[Observation, dict[str, Any]]:
        """Apply one action (A,) (clipped to [-1, 1]); returns the next observation and step info."""
        self._check_not_mid_rollout()
        a = self.check_action(action)
        self._stepped = True
        self.base.step(torch.as_tensor(a[None]))  # (1, A)
        self.step_count += 1
        self._last = self._evaluate()
        info = dict(self._last, step=self.step_count, truncated=self.step_count >= self.max_episode_steps)
        return self.observe(with_images), info

    @property
    def max_episode_steps(self) -> int:
        return self.config.episode_steps

    def _check_action_space(self) -> None:
        space = self.base.single_action_space
        if space.shape != (self.task.action_dim,) or not (np.all(space.low >= -1) and np.all(space.high <= 1)):
            raise ValueError(f"task {self.task.name}: controller {self.task.control_mode} takes actions in a box of "
                             f"shape {space.shape} from {space.low.min():g} to {space.high.max():g}, but the spec "
                             f"says {self.task.action_dim} entries in [-1, 1]; choose a normalised controller "
                             f"(pd_ee_delta_pose, pd_joint_delta_pos) and its size")

    def check_action(self, action: Any) -> np.ndarray:
        """Validate one action: shape (A,), finite; values outside [-1, 1] are clipped (documented)."""
        a = np.asarray(action, dtype=np.float32)
        if a.shape != (self.task.action_dim,):
            raise ValueError(f"action must have shape ({self.task.action_dim},) for task {self.task.name}, got "
                             f"{a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action must be finite, got {a.tolist()}; check the policy's output for NaN/inf")
        return np.clip(a, -1.0, 1.0)

    def _evaluate(self) -> dict[str, Any]:
        ev = self.adapter.evaluate()  # success, stage flags, metrics
        for s in self.task.stages:
            self.reached[s] |= ev[s]
        return ev

    def outcome(self) -> str:
        """The episode's outcome so far: success, or the outcome of the furthest stage reached before failing."""
        return self.task.outcome(bool(self._last.get("success")), self.reached)

    @property
    def metrics(self) -> dict[str, Any]:
        """The task's evaluation of the current state (privileged): ``success``, the stage flags and the
        task's continuous measures (``task.metrics``)."""
        return dict(self._last)

    @property
    def success(self) -> bool:
        return bool(self._last.get("success", False))

    # ------------------------------------------------------------------ observations
    def proprio(self) -> np.ndarray:
        """(P,) float32: the task's proprioception (its adapter reads it)."""
        return self.adapter.proprio()

    def privileged_state(self) -> dict[str, np.ndarray]:
        return self.adapter.privileged_state(self._last)

    def sim_state(self) -> np.ndarray:
        """ManiSkill's flat physics state (S,) float32: enough to restore poses and velocities and re-render."""
        return self.base.get_state()[0].numpy().astype(np.float32)

    def drive_targets(self) -> np.ndarray:
        return self.base.agent.robot.get_drive_targets()[0].numpy().astype(np.float32)

    def render(self, cameras: tuple[str, ...] | None = None, cull: bool | None = None) -> dict[str, np.ndarray]:
        """Render the current state: camera -> (H, W, 3) uint8 (default: the task's cameras). ``cull`` hides, per
        camera, the bodies wholly outside its view frustum while it draws: the same pixels, drawn faster. By default
        it culls unless a light of the scene casts shadows (a body outside the view could shade a pixel in it) or the
        physics runs on a GPU (whose poses the CPU side does not read back)."""
        b = self.base
        if cull is None:
            cull = not (b.gpu_sim_enabled or self._casts_shadows())
        b.scene.update_render(update_sensors=True, update_human_render_cameras=False)
        out = {}
        for name in cameras or self.task.cameras:
            cam = b.scene.sensors[name]
            hidden = self._outside_frustum(cam.camera._render_cameras[0]) if cull else []
            try:
                for body in hidden:
                    body.visibility = 0.0
                cam.capture()  # records and submits the draw now: visibility is read here
            finally:
                for body in hidden:
                    body.visibility = 1.0
            rgb = cam.get_obs(rgb=True, depth=False, position=False, segmentation=False)["rgb"]  # (1, H, W, 3)
            out[name] = rgb[0].cpu().numpy().copy()  # a GPU render backend returns CUDA tensors
        return out

    def _casts_shadows(self) -> bool:
        return any(light.shadow for light in self.base.scene.sub_scenes[0].render_system.lights)

    def _outside_frustum(self, cam) -> list:
        """The visible render bodies whose world AABB lies wholly outside ``cam``'s frustum (conservative: a
        body is hidden only if all 8 corners of its box fail one clip-space half-space)."""
        import sapien

        scene = self.base.scene.sub_scenes[0]  # a new object whenever ManiSkill rebuilds the scene
        if self._bodies is None or self._bodies[0] is not scene:
            comps = (e.find_component_by_type(sapien.render.RenderBodyComponent) for e in scene.entities)
            self._bodies = (scene, [c for c in comps if c is not None])
        pv = cam.get_projection_matrix() @ np.linalg.inv(cam.get_model_matrix())  # (4, 4) world -> clip
        bodies = [c for c in self._bodies[1] if c.visibility == 1.0]
        if not bodies:
            return []
        boxes = np.array([c.get_global_aabb_fast() for c in bodies])  # (K, 2, 3) min, max
        corners = boxes[:, _CORNERS, [0, 1, 2]]  # (K, 8, 3)
        x, y, z, w = (np.concatenate([corners, np.ones_like(corners[..., :1])], -1) @ pv.T).transpose(2, 0, 1)
        side = [np.all(x < -w, 1), np.all(x > w, 1), np.all(y < -w, 1), np.all(y > w, 1), np.all(w <= 0, 1),
                np.all(z > w, 1)]  # (K,) each: every corner beyond one plane
        return [c for c, o in zip(bodies, np.any(side, 0)) if o]

    def observe(self, with_images: bool = False) -> Observation:
        self._check_not_mid_rollout()
        return Observation(step=self.step_count, proprio=self.proprio(),
                           images=self.render() if with_images else None, state=self.privileged_state())

    # ------------------------------------------------------------------ snapshots
    def _controllers(self) -> dict[str, Any]:
        return self.base.agent.controller.controllers

    @torch.inference_mode(False)
    def snapshot(self) -> Snapshot:
        ctrl = {}
        for name, c in self._controllers().items():
            ctrl[name] = {k: _clone(getattr(c, k)) for k in ("_target_qpos", "_start_qpos", "_target_pose", "_step")
                          if getattr(c, k, None) is not None}
        return Snapshot(sim=_clone(self.base.get_state_dict()), controllers=ctrl,
                        drive_targets=self.base.agent.robot.get_drive_targets().clone(),
                        step=self.step_count, reached=dict(self.reached))

    @torch.inference_mode(False)
    def restore(self, snap: Snapshot) -> None:
        """Put the simulator back to ``snap``. Restore before re-executing what a restored rollout predicted:
        PhysX keeps hidden state from the previous rollout (cached contacts, we believe), so a restored
        rollout can differ by ~1e-3 m from one that was never restored; restoring once or twice is the same."""
        self._restore_sim(snap)
        self._mid_rollout = False
        self.step_count = snap.step
        self.reached = dict(snap.reached)
        self._last = self._evaluate()

    def _restore_sim(self, snap: Snapshot) -> None:
        """Physics, controllers, drive targets and ManiSkill's step counter; not wamplan's stage tracking."""
        self.base.set_state_dict(_clone(snap.sim))
        for name, c in self._controllers().items():
            for k, v in snap.controllers[name].items():
                setattr(c, k, _clone(v))
        robot = self.base.agent.robot
        robot.set_joint_drive_targets(snap.drive_targets.clone(), joints=robot.active_joints)
        self.base._elapsed_steps[:] = snap.step

    # ------------------------------------------------------------------ planning
    @torch.inference_mode(False)
    def simulate(self, snap: Snapshot, actions: np.ndarray, cameras: tuple[str, ...] | None = None) -> np.ndarray:
        """Candidate rollouts for a planner: actions (B, L, A) -> terminal views (B, V, H, W, 3) uint8 (default
        views: the task's cameras).

        Each candidate starts from ``snap`` (restored once) and runs the controller and physics only; its
        terminal state is bit-identical to ``restore(snap)`` then ``step`` over the same actions. The env is
        left at the last candidate's end without stage tracking: ``restore`` a snapshot before stepping or
        observing again (``step``/``observe`` refuse until then). A GPU env (``num_envs = B``, physx_cuda)
        would implement the same signature with one batched rollout.
        """
        acts = np.asarray(actions, dtype=np.float32)
        cameras = cameras or self.task.cameras
        if acts.ndim != 3 or acts.shape[-1] != self.task.action_dim:
            raise ValueError(f"actions must have shape (B, L, {self.task.action_dim}), got {acts.shape}")
        if not np.all(np.isfinite(acts)):
            raise ValueError("candidate actions must be finite; check the planner's samples for NaN/inf")
        acts = np.clip(acts, -1.0, 1.0)  # as step's check_action
        self._stepped = True
        views = []
        for cand in torch.from_numpy(acts):  # (L, A)
            self._restore_sim(snap)
            self._mid_rollout = True
            for a in cand:
                self.base._step_action(a[None])  # (1, A): controller + physics, as in base.step
            frames = self.render(cameras)
            views.append(np.stack([frames[c] for c in cameras]))  # (V, H, W, 3)
        return np.stack(views)  # (B, V, H, W, 3)

    def _check_not_mid_rollout(self) -> None:
        if self._mid_rollout:
            raise RuntimeError("the env is mid-rollout after simulate(); restore(snapshot) before stepping or "
                               "observing")

    def close(self) -> None:
        self._gym.close()
