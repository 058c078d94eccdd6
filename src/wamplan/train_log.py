"""Where a training run's curves go besides ``RUN/metrics.jsonl``: TensorBoard and W&B (``--log tensorboard wandb``).

Every trainer's loop (``wamplan.train_loop.train``) writes each metrics record to the file and hands it to one
:class:`RunLog`, which sends the same scalars under the same names to the backends the config's ``log`` names: every
number of the record (``lr``, ``train/...``, ``val/...``, ``samples_per_s``, ``epoch``) at its ``global_step``. At
each evaluation (epoch end) a trainer with pictures (a decoder's decoded views beside their targets, TinyWAM's
predicted views beside the real ones) logs them as images too.

    RUN/tensorboard/                 event files: ``tensorboard --logdir RUN/tensorboard``
    RUN/wandb/offline-run-.../       a W&B offline run (no account): ``wandb sync RUN/wandb/offline-run-...``

W&B runs offline unless the environment's ``WANDB_MODE`` says otherwise. Each backend is an optional extra
(``pip install 'wamplan[tensorboard]'``); :func:`require_backends` refuses a missing one in one line before training.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from wamplan.errors import UserError
from wamplan.train_config import LOGGERS  # the backends ``--log`` takes; each is also its extra's and package's name

TB_DIR, WANDB_DIR = "tensorboard", "wandb"  # in the run directory


def require_backends(names: Sequence[str]) -> None:
    """One line naming the extra to install for the first backend of ``names`` whose package is missing."""
    for name in names:
        if name not in LOGGERS:
            raise UserError(f"--log {name}: unknown logger; choose from {', '.join(LOGGERS)}")
        if importlib.util.find_spec(name) is None:
            raise UserError(f"--log {name} needs the {name} package, which is not installed: "
                            f"pip install 'wamplan[{name}]' (or drop --log {name})")


def scalars(record: dict[str, Any]) -> dict[str, float]:
    """The numbers of a metrics record that are logged as curves: all but its step (the x axis) and text fields."""
    return {k: float(v) for k, v in record.items()
            if k != "global_step" and isinstance(v, (int, float)) and not isinstance(v, bool)}


class RunLog:
    """The backends ``names`` of one training run in ``run_dir``; ``config`` is stored with a W&B run, ``kind``
    names it (``wm-predictor``, ``tinywam``, ...). ``resume_step``: the step a resumed run continues from (events
    TensorBoard holds past it, from a run stopped between a log line and a save, are dropped)."""

    def __init__(self, names: Sequence[str], run_dir: str | Path, kind: str, config: dict[str, Any] | None = None,
                 resume_step: int = 0) -> None:
        require_backends(names)
        run = Path(run_dir)
        self.tb = self.wandb = None
        if "tensorboard" in names:
            from torch.utils.tensorboard import SummaryWriter

            self.tb = SummaryWriter(str(run / TB_DIR), purge_step=resume_step + 1 if resume_step else None)
        if "wandb" in names:
            import wandb

            (run / WANDB_DIR).mkdir(parents=True, exist_ok=True)
            self.wandb = wandb.init(project="wamplan", name=run.name, job_type=kind, dir=str(run), config=config,
                                    mode=os.environ.get("WANDB_MODE", "offline"), reinit="create_new")
            self.wandb.define_metric("global_step")
            self.wandb.define_metric("*", step_metric="global_step")  # every curve against the loop's step

    def scalars(self, record: dict[str, Any]) -> None:
        """Log the numbers of one metrics.jsonl record (:func:`scalars`) at its ``global_step``."""
        step, values = record["global_step"], scalars(record)
        if self.tb is not None:
            for k, v in values.items():
                self.tb.add_scalar(k, v, step)
        if self.wandb is not None:
            # one row a record: a step record and an epoch record may share a step
            self.wandb.log({**values, "global_step": step})

    def images(self, pictures: dict[str, np.ndarray], step: int) -> None:
        """Log ``pictures`` (name -> (H, W, 3) uint8) at ``step``."""
        if self.tb is not None:
            for k, img in pictures.items():
                self.tb.add_image(k, img, step, dataformats="HWC")
        if self.wandb is not None and pictures:
            import wandb

            self.wandb.log({**{k: wandb.Image(img) for k, img in pictures.items()}, "global_step": step})

    def close(self) -> None:
        if self.tb is not None:
            self.tb.close()
        if self.wandb is not None:
            self.wandb.finish()


def beside_targets(pred: np.ndarray, target: np.ndarray) -> np.ndarray:
    """One picture of predictions beside their targets: row i is ``pred[i] | target[i]``; (B, H, W, 3) floats in
    [0, 1] each -> (B * H, 2 * W, 3) uint8."""
    rows = np.concatenate([pred, target], axis=2)  # (B, H, 2W, 3)
    return (np.clip(rows.reshape(-1, *rows.shape[2:]), 0, 1) * 255).round().astype(np.uint8)  # (B * H, 2W, 3)
