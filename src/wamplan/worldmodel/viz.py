"""Paper Figure 4: a ground-truth episode against the world model's autoregressive rollout from the same
context and actions, decoded to pixels (the decoder is only for looking). The camera shown is one of the world
model's (its checkpoint's cameras); the store must hold the model's task."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from wamplan.errors import UserError


@torch.inference_mode()
def rollout_figure(ckpt: str | Path, decoder: str | Path, store_dir: str | Path, *, episode: int = 0, start: int = 0,
                   steps: int = 12, camera: str | None = None, out: str | Path = "wm_viz.png",
                   compare: str | Path | None = None) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from wamplan.data.store import EpisodeStore
    from wamplan.plot import save_figure
    from wamplan.worldmodel.decoder import load_decoder
    from wamplan.worldmodel.load import load_world_model

    models = [("model", *load_world_model(ckpt))]
    if compare is not None:
        models.append(("compare", *load_world_model(compare)))
    cameras = models[0][1].cameras  # the views in the order the model stacks them
    for label, model, _ in models:
        if model.task.name != models[0][1].task.name or model.cameras != cameras:
            raise UserError(f"--compare {compare} was trained on task '{model.task.name}' with cameras "
                            f"{list(model.cameras)}, --ckpt {ckpt} on '{models[0][1].task.name}' with {list(cameras)}; "
                            f"compare world models of one task")
    camera = camera or cameras[0]
    if camera not in cameras:
        raise UserError(f"--camera {camera} is not a view of {ckpt}; its cameras are {list(cameras)}")
    dec = load_decoder(decoder, encoder=models[0][2], task=models[0][1].task.name)
    store = EpisodeStore(store_dir)
    if store.task_name != models[0][1].task.name:
        raise UserError(f"{store_dir} holds task '{store.task_name}' but {ckpt} was trained on task "
                        f"'{models[0][1].task.name}'; show an episode of its task")
    paths = store.episode_paths()
    if not 0 <= episode < len(paths):
        raise UserError(f"--episode {episode} is out of range: {store_dir} holds {len(paths)} episodes")
    ep = store.load(paths[episode])
    cfg, enc = models[0][1].cfg, models[0][2]
    d, hc, v = cfg.frameskip, cfg.context, cameras.index(camera)
    frame_steps = [start + i * d for i in range(hc + steps)]  # context frames, then the rollout's targets
    if frame_steps[-1] + d > ep.length:
        raise UserError(f"episode {episode} has {ep.length} steps; --start {start} with --steps {steps} at frameskip "
                        f"{d} needs {frame_steps[-1] + d}: lower --steps or --start")
    stored = list(ep.image_steps)
    missing = [t for t in frame_steps if t not in stored]
    if missing:
        raise UserError(f"steps {missing[:3]} have no stored images (stride {store.image_every}); pick --start a "
                        f"multiple of {store.image_every}")
    idx = [stored.index(t) for t in frame_steps]
    imgs = np.stack([ep.images[c][idx] for c in cameras], 1)  # (F, V, H, W, 3)
    z = enc.encode_batched(imgs.reshape(-1, *imgs.shape[2:])).half().float()  # (F·V, N, D), as cached: float16
    z = z.reshape(len(idx), len(cameras), *z.shape[1:])  # (F, V, N, D)
    q = torch.from_numpy(ep.proprio[frame_steps])  # (F, P)
    a = torch.from_numpy(np.stack([ep.actions[t:t + d].reshape(-1) for t in frame_steps]))  # (F, Δ·A)
    cols = sorted({0, *np.linspace(0, steps, 5).round().astype(int).tolist()})
    rows = [("ground truth", [imgs[hc - 1 + h, v] for h in cols])]
    for label, model, _ in models:
        zp, _ = model.rollout(z[None, :hc], q[None, :hc], a[None, :hc - 1], a[None, hc - 1:hc - 1 + steps])
        zs = torch.cat([z[None, hc - 1:hc], zp], 1)[0, :, v]  # (steps+1, N, D), h = 0 is the context frame
        pics = dec(zs[cols].to(next(dec.parameters()).device)).permute(0, 2, 3, 1).cpu().numpy()  # (C, S, S, 3)
        rows.append((f"{label}: {Path(ckpt if label == 'model' else compare).name}", list(pics)))
    fig, axes = plt.subplots(len(rows), len(cols), figsize=(2 * len(cols), 2.1 * len(rows)), squeeze=False)
    for r, (label, pics) in enumerate(rows):
        for j, h in enumerate(cols):
            ax = axes[r][j]
            ax.imshow(np.clip(pics[j], 0, 255 if pics[j].dtype == np.uint8 else 1))
            ax.set_xticks([]), ax.set_yticks([])
            if r == 0:
                ax.set_title(f"h={h} (+{h * d} steps)", fontsize=9)
            if j == 0:
                ax.set_ylabel(label, fontsize=8)
    fig.suptitle(f"{ep.source} seed {ep.seed} ({ep.outcome}), {camera} view, context from step {start}", fontsize=9)
    return save_figure(fig, out)
