"""TinyWAM's architecture config (:class:`TinyWAMConfig`), apart from the network (``wam.tinywam``) so that an
option parser and the presets read it without importing torch."""

from __future__ import annotations

from dataclasses import dataclass, replace

from wamplan.config import check_numbers, field, require
from wamplan.envs.spec import TaskSpec, get_task


@dataclass(frozen=True)
class TinyWAMConfig:
    """Architecture of TinyWAM (stored in the checkpoint; a checkpoint rebuilds exactly this network).
    ``action_dim``, ``proprio_dim`` and ``cameras`` of None are the task's: :meth:`for_task` fills them."""

    image_size: int = field(64, "side of the square images the model reads and predicts, pixels")
    chunk_length: int = field(16, "H, actions per chunk; the images are predicted for t + H")
    action_dim: int | None = field(None, "A, action size (default: the task's)")
    proprio_dim: int | None = field(None, "P, proprioception size (default: the task's)")
    cameras: tuple[str, ...] | None = field(None, "cameras read and predicted, in this order (default: the "
                                                  "training stores' cameras)")
    channels: tuple[int, ...] = field((16, 32, 64, 128), "conv channels of the encoder stages; each stage "
                                      "halves the resolution (the decoder mirrors them)")
    latent_dim: int = field(256, "L, size of one view's token and of the proprio embedding")
    trunk_dim: int = field(512, "T, size of the fused trunk feature both heads read")
    residual: bool = field(True, "predict the future views as a change of the current views (else directly)")

    def __post_init__(self) -> None:
        check_numbers(self)
        n = len(self.channels)
        require(n >= 1 and all(isinstance(c, int) and c > 0 for c in self.channels),
                f"TinyWAMConfig.channels must be positive ints, e.g. 16 32 64 128; got {self.channels}")
        require(isinstance(self.image_size, int) and self.image_size >= 2 ** n and self.image_size % 2 ** n == 0,
                f"TinyWAMConfig.image_size must be a multiple of 2^{n} = {2 ** n} (one halving per encoder stage); "
                f"got {self.image_size}: pick e.g. 64 or change --channels")
        for name in ("chunk_length", "action_dim", "proprio_dim", "latent_dim", "trunk_dim"):
            v = getattr(self, name)
            require(v is None and name in TASK_FIELDS or isinstance(v, int) and v > 0,
                    f"TinyWAMConfig.{name} must be a positive int, got {v!r}")
        require(self.cameras is None or len(self.cameras) >= 1 and len(set(self.cameras)) == len(self.cameras),
                f"TinyWAMConfig.cameras must be distinct camera names, got {self.cameras}")

    @property
    def grid(self) -> int:
        """Side of the encoder's last feature map."""
        return self.image_size // 2 ** len(self.channels)

    def for_task(self, task: str | TaskSpec, cameras: tuple[str, ...] | None = None) -> "TinyWAMConfig":
        """This config with the fields left None filled from ``task`` (``cameras``: the views the data holds,
        default the task's); one line when a set field does not fit the task (another action or proprio size,
        a camera the data lacks)."""
        spec = get_task(task)
        cameras = tuple(cameras) if cameras is not None else spec.cameras
        done = replace(self, action_dim=self.action_dim or spec.action_dim,
                       proprio_dim=self.proprio_dim or spec.proprio_dim, cameras=self.cameras or cameras)
        for name, want in (("action_dim", spec.action_dim), ("proprio_dim", spec.proprio_dim)):
            require(getattr(done, name) == want, f"TinyWAMConfig.{name} is {getattr(done, name)} but task "
                                                 f"{spec.name} has {want}; leave --{name.replace('_', '-')} unset")
        missing = [c for c in done.cameras if c not in cameras]
        require(not missing, f"TinyWAMConfig.cameras {list(done.cameras)} are not all among task {spec.name}'s "
                             f"cameras {list(cameras)}; pick --cameras from those (or leave it unset)")
        return done


TASK_FIELDS = ("action_dim", "proprio_dim", "cameras")  # TinyWAMConfig fields whose None means "the task's"
