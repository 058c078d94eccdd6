"""How to train TinyWAM (:class:`WAMTrainConfig`), apart from the trainer (``wam.train``) so that an option parser
and the presets read it without importing torch."""

from __future__ import annotations

from dataclasses import dataclass

from wamplan.config import check_numbers, field, require, with_default
from wamplan.train_config import LoopConfig

IMAGE_LOSSES = ("l1", "mse")


@dataclass(frozen=True)
class WAMTrainConfig(LoopConfig):
    """How to train TinyWAM: the loop's optimisation fields (:class:`~wamplan.train_loop.LoopConfig`, with
    TinyWAM's defaults), the loss, the augmentation, the validation split and the device."""

    epochs: int = with_default(LoopConfig, "epochs", 30)
    batch_size: int = with_default(LoopConfig, "batch_size", 32)
    lr: float = with_default(LoopConfig, "lr", 1e-3)
    weight_decay: float = with_default(LoopConfig, "weight_decay", 1e-4)
    min_lr_ratio: float = with_default(LoopConfig, "min_lr_ratio", 0.05)
    log_every_steps: int = with_default(LoopConfig, "log_every_steps", 10)
    image_weight: float = field(10.0, "lambda, weight of the image loss against the action MSE")
    image_loss: str = field("mse", "image loss: mse or l1 (on pixels in [0, 1])", choices=IMAGE_LOSSES)
    shift_pixels: int = field(4, "augmentation: random shift of each view by up to this many pixels (0: off)")
    val_fraction: float = field(0.1, "fraction of episodes held out for validation (by a hash of source and seed)")
    device: str = field("auto", "torch device: auto, cpu, cuda, cuda:1, mps, ...")

    def __post_init__(self) -> None:
        check_numbers(self)
        super().__post_init__()
        require(self.image_weight >= 0, f"WAMTrainConfig.image_weight must be >= 0, got {self.image_weight}")
        require(self.image_loss in IMAGE_LOSSES,
                f"WAMTrainConfig.image_loss must be one of {list(IMAGE_LOSSES)}, got {self.image_loss!r}")
        require(isinstance(self.shift_pixels, int) and self.shift_pixels >= 0,
                f"WAMTrainConfig.shift_pixels must be an int >= 0, got {self.shift_pixels!r}")
        require(0 <= self.val_fraction < 1, f"WAMTrainConfig.val_fraction must be in [0, 1), got {self.val_fraction}")
