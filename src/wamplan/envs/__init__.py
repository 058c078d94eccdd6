"""The ManiSkill 3 task ``CubeInsertion-v1`` and wamplan's thin wrapper around it.

``wamplan.envs.contract`` (re-exported here) is the task's contract and imports no simulator;
``wamplan.envs.task`` registers the task with ManiSkill when imported,
which ``wamplan.envs.core.InsertionEnv`` does on construction. Vulkan is configured here, before
any submodule can import SAPIEN.
"""

from wamplan.envs.vulkan import configure_vulkan

configure_vulkan()

from wamplan.envs.contract import (ACTION_DIM, CAMERAS, ENV_ID, MAX_EPISODE_STEPS, OUTCOMES,  # noqa: E402
                                   PROPRIO_DIM, STAGES, Observation)

__all__ = ["ACTION_DIM", "CAMERAS", "ENV_ID", "MAX_EPISODE_STEPS", "OUTCOMES", "PROPRIO_DIM", "STAGES",
           "Observation"]
