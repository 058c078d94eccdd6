"""Any ManiSkill 3 task as a wamplan task: :func:`maniskill_task` builds its :class:`TaskSpec` (read from the env
itself by :func:`spec_from_env`, or written out), and the built-in registrations below.

The generic reading (``wamplan.envs.adapters.ManiSkillAdapter``): the task's sensors are the cameras (a robot
with a wrist camera, ``panda_wristcam``, adds ``hand_camera``), proprio is the robot's joint positions then its
TCP pose (xyz, wxyz), success is ``evaluate()["success"]``, and the controller is a normalised delta controller
(``pd_ee_delta_pose`` by default: 6 arm entries, then the gripper, +1 open, -1 closed), and the planners'
sampling sigma is scaled to that controller's step (``TaskSpec.sigma_scale``).

Bringing another task (a plug-in module registers it when imported)::

    from wamplan.envs.maniskill import maniskill_task
    from wamplan.envs.spec import register_task
    register_task(maniskill_task("PickCube-v1", name="pick-cube", cameras=("base_camera",), action_dim=7,
                                 proprio_dim=16, max_episode_steps=100, instruction="pick up the cube"))

or, letting ManiSkill say the cameras and sizes (builds the env once)::

    register_task(spec_from_env("PickCube-v1", name="pick-cube", instruction="pick up the cube"))

For the command line (and its worker processes) to know the task, the plug-in's package names that module in the
entry-point group ``wamplan.tasks`` (pyproject.toml: ``[project.entry-points."wamplan.tasks"]``,
``my_tasks = "my_package.tasks"``); wamplan imports it the first time the registry of tasks is read.

This module imports neither ManiSkill nor torch; :func:`spec_from_env` does when called.
"""

from __future__ import annotations

from typing import Any

from wamplan.envs.spec import TaskSpec, register_task

GENERIC_ADAPTER = "wamplan.envs.adapters:ManiSkillAdapter"
MOTION_PLANNING = "maniskill-motion-planning"  # TaskSpec.demonstrations: ManiSkill's solver makes them


# ManiSkill's Panda delta controllers move 10 cm and 0.1 rad a step per unit action; TaskSpec.sigma_scale is relative
# to cube-insertion's 2 cm and 0.1 rad, so their translation entries get 0.2. Their three rotation entries get 0.1
# (0.001 rad a step at the default sigma), since the cube's one rotation is a yaw and these tilt the hand about
# every axis. The gripper entry gets 1.
ARM_SIGMA_SCALE = {"pd_ee_delta_pos": (0.2, 0.2, 0.2), "pd_ee_delta_pose": (0.2, 0.2, 0.2, 0.1, 0.1, 0.1)}


def maniskill_task(env_id: str, *, name: str, cameras: tuple[str, ...], action_dim: int, proprio_dim: int,
                   max_episode_steps: int, instruction: str, control_mode: str = "pd_ee_delta_pose",
                   gripper_index: int | None = -1, chunk_len: int = 16, env_kwargs: dict[str, Any] | None = None,
                   **more: Any) -> TaskSpec:
    """The spec of a ManiSkill env read the generic way. ``gripper_index=-1``: the last action entry (ManiSkill's
    Panda controllers); ``None``: no gripper. ``more``: other :class:`TaskSpec` fields (stages, metrics, ...)."""
    if gripper_index is not None and gripper_index < 0:
        gripper_index += action_dim
    arm = ARM_SIGMA_SCALE.get(control_mode, ())
    if "sigma_scale" not in more and arm and len(arm) + (gripper_index is not None) == action_dim:
        more["sigma_scale"] = arm + (1.0,) * (gripper_index is not None)  # the gripper is the last entry
    return TaskSpec(name=name, env_id=env_id, cameras=tuple(cameras), action_dim=action_dim, proprio_dim=proprio_dim,
                    control_mode=control_mode, max_episode_steps=max_episode_steps, instruction=instruction,
                    adapter=more.pop("adapter", GENERIC_ADAPTER), gripper_index=gripper_index, chunk_len=chunk_len,
                    env_kwargs=tuple(sorted((env_kwargs or {}).items())), **more)


def spec_from_env(env_id: str, *, name: str, instruction: str, control_mode: str = "pd_ee_delta_pose",
                  max_episode_steps: int | None = None, **more: Any) -> TaskSpec:
    """:func:`maniskill_task` with the cameras, action and proprio sizes and episode length read from one
    instance of the env (CPU simulator and renderer)."""
    import gymnasium as gym

    import wamplan.envs  # noqa: F401  (configures Vulkan before SAPIEN loads)
    import mani_skill.envs  # noqa: F401  (registers ManiSkill's own tasks)
    from wamplan.envs.adapters import ManiSkillAdapter

    env = gym.make(env_id, obs_mode="state_dict", control_mode=control_mode, num_envs=1, sim_backend="physx_cpu",
                   render_backend="cpu", **more.get("env_kwargs", {}))
    try:
        base = env.unwrapped
        base.reset(seed=0)
        probe = maniskill_task(env_id, name=name, cameras=("_",), action_dim=1, proprio_dim=1, max_episode_steps=1,
                               instruction=instruction, gripper_index=None)
        cameras = tuple(base.scene.sensors)
        action_dim = int(base.single_action_space.shape[0])
        proprio_dim = int(ManiSkillAdapter(probe, base).proprio().shape[0])
        steps = max_episode_steps or int(gym.spec(env_id).max_episode_steps or 200)
    finally:
        env.close()
    return maniskill_task(env_id, name=name, cameras=cameras, action_dim=action_dim, proprio_dim=proprio_dim,
                          max_episode_steps=steps, instruction=instruction, control_mode=control_mode, **more)


# ManiSkill's peg-in-hole (3 mm clearance), solved by ManiSkill's motion planner, whose demonstrations run longer
# than ManiSkill's own 100-step limit (set for faster policies): episodes here run up to 200 steps.
PEG_INSERTION_SIDE = register_task(maniskill_task(
    "PegInsertionSide-v1", name="peg-insertion-side", cameras=("base_camera", "hand_camera"), action_dim=7,
    proprio_dim=16, max_episode_steps=200, instruction="insert the peg into the hole in the box, sideways",
    demonstrations=MOTION_PLANNING, adapter="wamplan.envs.adapters:PegInsertionSideAdapter", stages=("grasped",),
    outcomes=(("grasped", "grasped_not_inserted"),), failure="never_grasped"))
# Small tasks of ManiSkill's tutorial set (PushCube's Panda has no wrist camera).
PUSH_CUBE = register_task(maniskill_task(
    "PushCube-v1", name="push-cube", cameras=("base_camera",), action_dim=7, proprio_dim=16, max_episode_steps=50,
    instruction="push the cube to the goal region", demonstrations=MOTION_PLANNING))
STACK_CUBE = register_task(maniskill_task(
    "StackCube-v1", name="stack-cube", cameras=("base_camera", "hand_camera"), action_dim=7, proprio_dim=16,
    max_episode_steps=200, instruction="stack the red cube on the green cube",
    stages=("is_cubeA_grasped", "is_cubeA_on_cubeB"),
    outcomes=(("is_cubeA_on_cubeB", "stacked_not_released"), ("is_cubeA_grasped", "grasped_not_stacked")),
    failure="never_grasped", demonstrations=MOTION_PLANNING, adapter="wamplan.envs.adapters:StackCubeAdapter"))
