"""Tasks: the registry of task specs (``wamplan.envs.spec``), the ManiSkill 3 task ``CubeInsertion-v1`` (its
contract in ``wamplan.envs.contract``), any ManiSkill task (``wamplan.envs.maniskill``), and ``TaskEnv``, the thin
wrapper every layer above steps.

Importing this package registers ``CubeInsertion-v1`` with gymnasium lazily, without importing ManiSkill:
the first ``gym.make("CubeInsertion-v1", ...)`` imports ``wamplan.envs.task``, whose ManiSkill registration
(``register_env``) then takes the placeholder's place. Vulkan is configured here, before any submodule can
import SAPIEN.
"""

from wamplan.envs.vulkan import configure_vulkan

configure_vulkan()

from wamplan.envs.contract import ENV_ID, MAX_EPISODE_STEPS  # noqa: E402
from wamplan.envs.spec import TASKS, Observation, TaskSpec, get_task, register_task  # noqa: E402


def _register_lazily() -> None:
    """A gymnasium spec equal to ManiSkill's (time limit wrapper, no gymnasium checker) whose entry point
    imports the task only when an env is made."""
    import gymnasium as gym
    from gymnasium.envs.registration import WrapperSpec

    if ENV_ID in gym.registry:  # wamplan.envs.task is already imported: ManiSkill's own spec stands
        return
    limit = WrapperSpec("MSTimeLimit", entry_point="mani_skill.utils.registration:TimeLimitWrapper",
                        kwargs=dict(max_episode_steps=MAX_EPISODE_STEPS))
    gym.register(ENV_ID, entry_point="wamplan.envs.task:make_env", max_episode_steps=MAX_EPISODE_STEPS,
                 disable_env_checker=True, additional_wrappers=(limit,))


_register_lazily()

__all__ = ["TASKS", "Observation", "TaskSpec", "get_task", "register_task"]
