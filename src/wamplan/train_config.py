"""The optimisation configs every trainer shares (:class:`LoopConfig`, :class:`AdamWConfig`), apart from the loop
(``wamplan.train_loop``) so that an option parser reads them without importing torch."""

from __future__ import annotations

from dataclasses import dataclass

from wamplan.config import check_numbers, field, require
from wamplan.errors import SEED_LIMIT

# fields of a config's "train" section that may change when a run is resumed (everything else must match)
RUN_ONLY_FIELDS = ("epochs", "num_workers", "device", "save_every_steps", "log_every_steps", "precision", "log")

PRECISIONS = ("float32", "bfloat16")
LOGGERS = ("tensorboard", "wandb")  # where ``log`` also sends the curves (``wamplan.train_log``)


@dataclass(frozen=True)
class LoopConfig:
    """The optimisation fields every trainer shares and the loop reads. The trainers' configs extend it
    (``wam.train.WAMTrainConfig``; ``worldmodel.config.TrainConfig`` and ``DecoderTrainConfig`` through
    :class:`AdamWConfig`), redeclaring a default with :func:`wamplan.config.with_default` where theirs differs."""

    epochs: int = field(24, "passes over the training set (raise it and re-run to train a finished run longer)")
    batch_size: int = field(24, "items per optimisation step")
    lr: float = field(5e-5, "peak learning rate (AdamW)")
    weight_decay: float = field(1e-3, "AdamW weight decay (on weight matrices and kernels only)")
    warmup_epochs: float = field(1.0, "linear warm-up length in epochs, then cosine decay")
    min_lr_ratio: float = field(0.0, "the cosine decays to lr * min_lr_ratio")
    grad_clip: float = field(1.0, "clip the global gradient norm to this (0: no clipping)")
    seed: int = field(0, "seed of the initialisation, the data order and any augmentation")
    num_workers: int = field(0, "worker processes that read the training data")
    save_every_steps: int = field(0, "also checkpoint every this many steps (0: at epoch ends only)")
    log_every_steps: int = field(0, "also log the running training losses to metrics.jsonl every this many steps "
                                     "(0: at epoch ends only)")
    precision: str = field("float32", "arithmetic of the forward pass and the loss: 'float32', or 'bfloat16' "
                                      "(autocast: matrix products in bfloat16; weights, gradients and the "
                                      "optimiser stay float32), on a CPU or a GPU")
    log: tuple[str, ...] = field((), "also log the metrics.jsonl scalars (same names, at their global_step) and, where "
                                     "the model draws pictures, predicted views beside their targets at each "
                                     "epoch's validation, to TensorBoard (RUN/tensorboard) and/or W&B (offline "
                                     "run in RUN/wandb; no account); each needs its extra: "
                                     "pip install 'wamplan[tensorboard]'", choices=LOGGERS)

    def __post_init__(self) -> None:
        check_numbers(self)
        name = type(self).__name__
        for k in ("epochs", "batch_size"):
            v = getattr(self, k)
            require(isinstance(v, int) and v > 0, f"{name}.{k} must be a positive int, got {v!r}")
        require(self.lr > 0, f"{name}.lr must be > 0, got {self.lr}; pass a positive --lr")
        require(self.weight_decay >= 0, f"{name}.weight_decay must be >= 0, got {self.weight_decay}")
        require(0 <= self.warmup_epochs <= self.epochs,
                f"{name}.warmup_epochs must be in [0, epochs={self.epochs}], got {self.warmup_epochs}")
        require(0 <= self.min_lr_ratio <= 1, f"{name}.min_lr_ratio must be in [0, 1], got {self.min_lr_ratio}")
        require(self.grad_clip >= 0, f"{name}.grad_clip must be >= 0 (0 disables it), got {self.grad_clip}")
        require(0 <= self.seed < SEED_LIMIT, f"--seed {self.seed}: seeds must lie in 0 .. {SEED_LIMIT - 1}; pass "
                                             f"one in that range")
        for k in ("num_workers", "save_every_steps", "log_every_steps"):
            require(getattr(self, k) >= 0, f"{name}.{k} must be >= 0, got {getattr(self, k)}")
        require(all(x in LOGGERS for x in self.log) and len(set(self.log)) == len(self.log),
                f"{name}.log must name each of {', '.join(LOGGERS)} at most once, got {list(self.log)}")
        require(self.precision in PRECISIONS, f"{name}.precision must be one of {', '.join(PRECISIONS)}, got "
                                              f"{self.precision!r}; pass --precision float32 or bfloat16")


@dataclass(frozen=True)
class AdamWConfig(LoopConfig):
    """:class:`LoopConfig` with AdamW's betas as an option (``worldmodel.config.TrainConfig`` and
    ``DecoderTrainConfig`` extend it); :func:`fit` uses them (other configs: ``optim.make_adamw``'s default)."""

    betas: tuple[float, ...] = field((0.9, 0.999), "AdamW betas")

    def __post_init__(self) -> None:
        check_numbers(self)
        super().__post_init__()
        require(len(self.betas) == 2 and all(0 <= b < 1 for b in self.betas),
                f"{type(self).__name__}.betas must be two numbers in [0, 1), got {self.betas}")
