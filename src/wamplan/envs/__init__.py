"""The ManiSkill 3 task ``CubeInsertion-v1`` (registered on import) and wamplan's thin wrapper around it."""

from wamplan.envs.vulkan import configure_vulkan

configure_vulkan()

from wamplan.envs import task as _task  # noqa: E402  (registers CubeInsertion-v1 and the agent)
from wamplan.envs.task import ENV_ID, MAX_EPISODE_STEPS, STAGES  # noqa: E402

__all__ = ["ENV_ID", "MAX_EPISODE_STEPS", "STAGES"]
