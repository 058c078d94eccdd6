"""The env's settings, :class:`EnvConfig`: which registered task ``TaskEnv`` builds and how (camera size, the cube
task's geometry, episode length, ManiSkill's backends). Like ``wamplan.envs.spec`` it imports no simulator, so the
command line can offer its options (``wamplan collect --help``) without loading ManiSkill."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from wamplan.config import check_numbers, field, require
from wamplan.envs.spec import TASKS, TaskSpec, get_task

# ManiSkill's backend names (mani_skill/envs/utils/system/backend.py); a CUDA one may name a device (cuda:1)
SIM_BACKENDS = ("physx_cpu", "cpu", "physx_cuda", "cuda", "gpu")
RENDER_BACKENDS = ("cpu", "gpu", "cuda", "sapien_cpu", "sapien_cuda", "none")


@dataclass(frozen=True)
class EnvConfig:
    task: str = field("cube-insertion", "the registered task (`wamplan tasks` lists them)", listed=lambda: TASKS)
    camera_size: int = field(224, "rendered image side in pixels, every camera")
    clearance: float = field(0.002, "cube-insertion: gap between cube and hole wall per side, metres")
    cube_half_size: float = field(0.02, "cube-insertion: half the cube's side, metres")
    mount_height: float = field(0.025, "cube-insertion: height of the mount (depth of the hole), metres")
    robot_init_qpos_noise: float = field(0.02, "cube-insertion: std of the initial joint-angle noise, radians")
    max_episode_steps: int | None = field(None, "episodes truncate after this many control steps (default: the "
                                                "task's)")
    sim_backend: str = field("physx_cpu", "ManiSkill sim backend: physx_cpu (one env per process) or physx_cuda "
                             "(cuda:N for a device)")
    render_backend: str = field("cpu", "ManiSkill render backend: cpu (lavapipe), gpu, cuda:N (a device), or none "
                                "(no camera views: state-only rollouts; eval and collect refuse it)")

    def __post_init__(self):
        check_numbers(self)
        get_task(self.task)  # one line naming the registered tasks if unknown
        for flag, name, known in (("--sim-backend", self.sim_backend, SIM_BACKENDS),
                                  ("--render-backend", self.render_backend, RENDER_BACKENDS)):
            kind, _, index = name.partition(":")
            require(kind in known and (not index or (index.isdigit() and "cuda" in kind)),
                    f"{flag} {name!r} is not a ManiSkill backend; pass one of {', '.join(known)} (a CUDA one may "
                    f"name its device, e.g. cuda:1)")
        if self.sim_backend.partition(":")[0] not in ("physx_cpu", "cpu"):
            import torch

            require(torch.cuda.is_available(), f"--sim-backend {self.sim_backend} simulates on a GPU, but torch finds "
                                               f"no CUDA device here; pass --sim-backend physx_cpu")
        require(16 <= self.camera_size <= 1024, f"--camera-size must be in [16, 1024], got {self.camera_size}")
        require(0 < self.clearance < self.cube_half_size,
                f"--clearance must be in (0, --cube-half-size={self.cube_half_size}), got {self.clearance}")
        require(self.max_episode_steps is None or self.max_episode_steps > 0,
                f"--max-episode-steps must be > 0, got {self.max_episode_steps}")

    def require_views(self) -> None:
        """One line if this env cannot render the task's camera views (``render_backend`` none), which every
        policy of a WAM and every recorded episode needs."""
        require(self.render_backend != "none", f"--render-backend none renders no camera views, but the task's "
                f"views ({', '.join(self.spec.cameras)}) are needed here; pass --render-backend cpu (or gpu)")

    @property
    def spec(self) -> TaskSpec:
        return get_task(self.task)

    @property
    def episode_steps(self) -> int:
        """Control steps before an episode truncates: ``max_episode_steps``, or the task's."""
        return self.max_episode_steps or self.spec.max_episode_steps

    def task_kwargs(self) -> dict[str, Any]:
        """The kwargs that define the task's physics and pictures (what must match across a dataset)."""
        spec = self.spec
        kw = dict(task=spec.name, env_id=spec.env_id, control_mode=spec.control_mode, camera_size=self.camera_size)
        kw.update({name: getattr(self, name) for name in spec.config_kwargs})
        return kw
