"""How well a foreground readout reads the WAM's predicted pictures, from which the object-centric cost takes its
weights (``eval --cost-foreground``).

At every chunk boundary t + H of a WAM's open-loop episodes, the readout's foreground share of each patch token is
read from the WAM's prediction of the frame at t + H (made at t) and from the real frame at t + H, and both are
compared with the simulator's segmentation of the real frame:

    python lab/representation/foreground_reading.py --wam checkpoints/mini/tinywam --wm checkpoints/mini/wm_augmented \\
        --readout checkpoints/candidates/fg_cube --seeds 3016-3019 [--picture OUT.png] [--json OUT.json]

Prints, per camera, the mean absolute error of the share on the WAM's prediction and on the real frame, and the
share of the cost's weight (at ``--background-weight``) that foreground tokens carry.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from wamplan.config import int_list
from wamplan.encoders.foreground import cost_weights, load_foreground, token_fractions
from wamplan.envs.config import EnvConfig
from wamplan.envs.core import TaskEnv
from wamplan.policies.rollout import run_episode
from wamplan.wam import WAMPolicy, load_wam
from wamplan.worldmodel.load import load_world_model


def readings(wam_path: str, wm_path: str, readout_path: str, seeds: list[int], camera_size: int = 224):
    """Per boundary: (V, N) arrays ``wam`` (the readout on the WAM's prediction), ``real`` (on the real frame),
    ``truth`` (the segmentation's share), and the pictures (V, h, w, 3) ``wam_pictures`` and ``real_pictures``."""
    wam = load_wam(wam_path, device="cpu")
    predictor, encoder = load_world_model(wm_path)
    readout = load_foreground(readout_path, encoder, wam.task.name, predictor.cameras or wam.task.cameras)
    cams, grid = predictor.cameras or wam.task.cameras, int(round(encoder.num_patches ** 0.5))
    env = TaskEnv(EnvConfig(task=wam.task.name, camera_size=camera_size))
    policy = WAMPolicy(wam)
    H = policy.chunk_length
    out: dict[str, list] = {"wam": [], "real": [], "truth": [], "wam_pictures": [], "real_pictures": []}

    def read(pictures: dict) -> np.ndarray:
        with torch.no_grad():
            z = torch.stack([encoder.encode(pictures[c])[0] for c in cams])  # (V, N, D)
            return readout(z).numpy()  # (V, N)

    def at_boundary(env: TaskEnv, obs, action) -> None:
        if obs.step == 0 or obs.step % H or policy.last_output is None:
            return
        predicted = policy.last_output.images  # the WAM's picture of this frame, made H steps ago
        pictures, fg = env.render_foreground(cams)
        out["wam"].append(read(predicted))
        out["real"].append(read(pictures))
        out["truth"].append(token_fractions(np.stack([fg[c] for c in cams])[None], grid)[0])
        out["wam_pictures"].append(np.stack([predicted[c] for c in cams]))
        out["real_pictures"].append(np.stack([pictures[c] for c in cams]))

    for seed in seeds:
        run_episode(env, policy, seed, on_obs=at_boundary)
        print(f"seed {seed}: {len(out['wam'])} boundaries so far", flush=True)
    env.close()
    return {k: np.stack(v) for k, v in out.items()}, cams


def summary(r: dict, cams, background_weight: float) -> dict:
    w = cost_weights(r["wam"], background_weight)  # (B, V, N) the cost's weights
    fg = r["truth"] > 0.5  # (B, V, N) tokens mostly foreground
    return {c: {"mae_wam": float(np.abs(r["wam"][:, i] - r["truth"][:, i]).mean()),
                "mae_real": float(np.abs(r["real"][:, i] - r["truth"][:, i]).mean()),
                "foreground_tokens": float(fg[:, i].mean()),
                "weight_on_foreground": float((w[:, i] * fg[:, i]).sum() / w[:, i].sum())}
            for i, c in enumerate(cams)}


def draw(r: dict, cams, out: str, count: int = 4) -> None:
    import matplotlib.pyplot as plt

    from wamplan.plot import save_figure

    idx = np.linspace(0, len(r["wam"]) - 1, count).round().astype(int)
    g = int(round(r["wam"].shape[-1] ** 0.5))
    fig, axes = plt.subplots(count, 4 * len(cams), figsize=(1.7 * 4 * len(cams), 1.8 * count), squeeze=False)
    for row, b in enumerate(idx):
        for c, cam in enumerate(cams):
            panels = [(r["wam_pictures"][b, c], f"{cam}: WAM's"), (r["wam"][b, c].reshape(g, g), "readout"),
                      (r["real_pictures"][b, c], "real"), (r["truth"][b, c].reshape(g, g), "true share")]
            for k, (img, title) in enumerate(panels):
                ax = axes[row, 4 * c + k]
                ax.imshow(img, vmin=0, vmax=1, cmap="magma") if img.ndim == 2 else ax.imshow(img)
                ax.set_title(title, fontsize=7)
                ax.axis("off")
    save_figure(fig, out, dpi=70)


def main() -> None:
    p = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    p.add_argument("--wam", required=True)
    p.add_argument("--wm", required=True, help="the world model whose encoder the readout reads")
    p.add_argument("--readout", required=True, help="a foreground readout (`wamplan wm foreground`)")
    p.add_argument("--seeds", required=True, help="episode seeds, e.g. 3016-3019")
    p.add_argument("--background-weight", type=float, default=0.1)
    p.add_argument("--picture", default="")
    p.add_argument("--json", default="")
    args = p.parse_args()
    r, cams = readings(args.wam, args.wm, args.readout, int_list(args.seeds, "--seeds"))
    s = summary(r, cams, args.background_weight)
    print(f"{len(r['wam'])} boundaries; mean absolute error of each token's foreground share")
    print(f"{'camera':>8} {'on the WAM prediction':>22} {'on the real frame':>18} {'tokens > half fg':>17} "
          f"{'cost weight on them':>20}")
    for c, v in s.items():
        print(f"{c:>8} {v['mae_wam']:22.3f} {v['mae_real']:18.3f} {v['foreground_tokens']:17.3f} "
              f"{v['weight_on_foreground']:20.3f}")
    if args.picture:
        draw(r, cams, args.picture)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"boundaries": len(r["wam"]), "cameras": s}, fh, indent=1)


if __name__ == "__main__":
    from wamplan.errors import run_script

    run_script(main, "foreground_reading")
