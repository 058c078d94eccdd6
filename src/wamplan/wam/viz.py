"""A WAM's predicted t+H views beside the real ones, at a few chunk boundaries of a stored episode of the WAM's
task, for each of the WAM's cameras."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from wamplan.envs.spec import Observation
from wamplan.errors import UserError
from wamplan.plot import save_figure


def prediction_figure(wam, store_dir: str | Path, episode: int = 0, starts: tuple[int, ...] = (16, 48, 80),
                      out: str | Path = "wam_pred.png") -> dict[str, float]:
    """Rows: chunk starts t; per view: current | predicted t+H | real t+H. Returns per-view MSE (0-1 pixels)
    of the prediction and of copying the current view."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import torch

    from wamplan.data.store import EpisodeStore
    from wamplan.wam.tinywam import to_model_frames

    store = EpisodeStore(store_dir)
    if store.task_name != wam.task.name:
        raise UserError(f"{store_dir} holds task '{store.task_name}' but WAM '{wam.name}' acts in task "
                        f"'{wam.task.name}'; show an episode of its task")
    cameras = tuple(wam.cameras)
    paths = store.episode_paths()
    if not 0 <= episode < len(paths):
        raise UserError(f"--episode {episode} is out of range: {store_dir} holds {len(paths)} episodes")
    ep = store.load(paths[episode])
    steps, h = list(ep.image_steps), wam.chunk_length
    starts = tuple(t for t in starts if t in steps and min(t + h, ep.length) in steps)
    if not starts:
        raise UserError(f"no chunk start with stored images at t and t+{h} in episode {episode} ({ep.length} steps)")
    fig, axes = plt.subplots(len(starts), 3 * len(cameras), figsize=(1.6 * 3 * len(cameras), 1.8 * len(starts)),
                             squeeze=False)
    err: dict[str, list[float]] = {}
    for r, t in enumerate(starts):
        k, k2 = steps.index(t), steps.index(min(t + h, ep.length))
        obs = Observation(step=t, proprio=ep.proprio[t], images={c: ep.images[c][k] for c in cameras})
        pred = wam.predict(obs, getattr(wam, "default_instruction", ""))
        for v, c in enumerate(cameras):
            size = pred.images[c].shape[0]
            cur, real = (to_model_frames(torch.from_numpy(ep.images[c][j]), size).permute(1, 2, 0).numpy()
                         for j in (k, k2))
            err.setdefault(f"{c}_pred_mse", []).append(float(((pred.images[c] / 255.0 - real / 255.0) ** 2).mean()))
            err.setdefault(f"{c}_copy_mse", []).append(float(((cur / 255.0 - real / 255.0) ** 2).mean()))
            for j, (img, title) in enumerate(((cur, f"{c} t={t}"), (pred.images[c], f"predicted t+{h}"),
                                              (real, f"real t+{h}"))):
                ax = axes[r][3 * v + j]
                ax.imshow(img)
                ax.set_xticks([]), ax.set_yticks([])
                ax.set_title(title, fontsize=7)
    fig.suptitle(f"{ep.source} seed {ep.seed}: WAM predictions of the views {h} steps ahead", fontsize=9)
    save_figure(fig, out)
    return {k: float(np.mean(v)) for k, v in err.items()}
