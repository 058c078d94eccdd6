"""Pictures and videos of the task's cameras: the views side by side, in ``CAMERAS`` order."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from wamplan.envs.contract import CAMERAS


def side_by_side(views: dict[str, np.ndarray]) -> np.ndarray:
    """camera -> (H, W, 3) uint8 images -> one (H, len(CAMERAS) * W, 3) image, front | side | wrist."""
    return np.concatenate([views[c] for c in CAMERAS], axis=1)


def save_views(images: dict[str, np.ndarray], path: str | Path) -> None:
    """Write the views of one step side by side as an image file (format from the suffix)."""
    import imageio.v3 as iio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, side_by_side(images))


def write_video(path: str | Path, frames: list[dict[str, np.ndarray]], fps: int = 20) -> None:
    """Write one MP4 of per-step views (each camera -> (H, W, 3) uint8), the cameras side by side."""
    import imageio.v2 as imageio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with imageio.get_writer(path, fps=fps, macro_block_size=1) as w:
        for views in frames:
            w.append_data(side_by_side(views))
