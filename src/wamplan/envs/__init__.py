"""The ManiSkill 3 task ``CubeInsertion-v1`` and wamplan's thin wrapper around it.

``wamplan.envs.contract`` (re-exported here) is the task's contract and imports no simulator.
Importing this package registers ``CubeInsertion-v1`` with gymnasium lazily, without importing ManiSkill:
the first ``gym.make("CubeInsertion-v1", ...)`` imports ``wamplan.envs.task``, whose ManiSkill registration
(``register_env``) then takes the placeholder's place. Vulkan is configured here, before any submodule can
import SAPIEN.
"""

from wamplan.envs.vulkan import configure_vulkan

configure_vulkan()

from wamplan.envs.contract import (ACTION_DIM, CAMERAS, ENV_ID, MAX_EPISODE_STEPS, OUTCOMES,  # noqa: E402
                                   PROPRIO_DIM, STAGES, Observation)


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

__all__ = ["ACTION_DIM", "CAMERAS", "ENV_ID", "MAX_EPISODE_STEPS", "OUTCOMES", "PROPRIO_DIM", "STAGES",
           "Observation"]
