"""Sibling chunks in pictures: for one counterfactual branch group of a store, each sibling's real view K frames
into its chunk beside the decoded predictions of one or more world models (same context, each sibling's own
actions), so one sees whether a model moves its prediction with the chunk as the world does.

    python lab/representation/wm_sibling_picture.py STORE --wm shipped=checkpoints/mini/wm_augmented,new=RUN \\
        --decoder checkpoints/mini/decoder --camera wrist --group 0 --out sib.png

Each model reads the store's cached features of its own encoder, and the decoder must be one of that encoder. (A model
on a ``concat`` encoder was drawn through its first part the decoder was trained on, and one on ``object-masks`` tokens
also as the class maps they hold; those encoders left the core at stop 78: commits 9c6eb5d and f07acf1 or earlier.)
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch


def drawer(encoder, decoder_path, task=None):
    """(decoder, tokens -> the decoder's tokens, the part drawn or '') for a model's encoder; a decoder of another
    encoder is refused in one line."""
    from wamplan.checkpoint import checkpoint_dir, read_config
    from wamplan.data.features import feature_key
    from wamplan.errors import UserError
    from wamplan.worldmodel.decoder import KIND, load_decoder

    dec = load_decoder(decoder_path, task=task)  # its kind and task, each refused as such
    theirs = read_config(checkpoint_dir(decoder_path), KIND).get("encoder")
    if theirs and feature_key(theirs) != feature_key(encoder.config_dict()):
        raise UserError(f"decoder {decoder_path} was trained on another encoder's tokens than {encoder.config_dict()}; "
                        f"pass a decoder of that encoder")
    return dec, (lambda z: z), ""


@torch.inference_mode()
def main(argv: list[str] | None = None) -> Path:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("store", type=Path, help="a store with counterfactual branches (collect --branches)")
    p.add_argument("--wm", required=True, help="LABEL=CHECKPOINT, comma separated")
    p.add_argument("--decoder", required=True, help="a decoder of the models' encoder")
    p.add_argument("--camera", default="wrist")
    p.add_argument("--group", type=int, default=0, help="which branch group of the validation split")
    p.add_argument("--horizon", type=int, default=4, help="frames into the chunk (4 = the chunk's end at Δ 4)")
    p.add_argument("--siblings", type=int, default=4)
    p.add_argument("--out", type=Path, default=Path("wm_siblings.png"))
    args = p.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from wamplan.data.features import feature_key
    from wamplan.data.readers import BranchGroups
    from wamplan.errors import UserError
    from wamplan.plot import save_figure
    from wamplan.worldmodel.load import load_world_model

    pairs = [s.partition("=") for s in args.wm.split(",")]
    if any(not lab or not path for lab, _, path in pairs):
        raise UserError(f"--wm {args.wm!r}: give LABEL=CHECKPOINT for every model, comma separated "
                        f"(e.g. shipped=checkpoints/mini/wm_augmented)")
    models = [(lab, *load_world_model(path)) for lab, _, path in pairs]
    cfg = models[0][1].cfg
    cameras = list(models[0][1].cameras or ())
    if args.camera not in cameras:
        raise UserError(f"--camera {args.camera}: the models read {', '.join(cameras) or 'views of no named camera'}")
    if args.siblings < 1:
        raise UserError(f"--siblings {args.siblings}: draw 1 or more")
    if args.horizon < 1:
        raise UserError(f"--horizon {args.horizon}: give 1 or more frames into the chunk")
    pics = BranchGroups([args.store], cfg.frameskip, cfg.context, args.horizon, split="val")
    if not 0 <= args.group < len(pics):
        raise UserError(f"--group {args.group}: {args.store} has {len(pics)} branch groups in its validation split "
                        f"(collect counterfactual branches with `wamplan collect --branches`)")
    pics = pics[args.group]
    groups = {}  # one branch group per encoder: z (G, T, V, N, D)
    for _, _, enc in models:
        key = feature_key(enc.config_dict())
        if key not in groups:
            groups[key] = BranchGroups([args.store], cfg.frameskip, cfg.context, args.horizon, split="val",
                                       features=key)[args.group]
    v, hc, k = cameras.index(args.camera), cfg.context, args.horizon  # images (G, T, V, H, W, 3)
    n = min(args.siblings, pics["images"].shape[0])
    draw = [drawer(enc, args.decoder, model.task.name) for _, model, enc in models]
    rows = []
    for i in range(n):
        row = [("real", pics["images"][i, hc - 1 + k, v].numpy())]
        for (label, model, enc), (dec, tokens, part) in zip(models, draw):
            g = groups[feature_key(enc.config_dict())]
            z, q, a = g["z"][i:i + 1].float(), g["q"][i:i + 1].float(), g["a"][i:i + 1].float()
            zp, _ = model.rollout(z[:, :hc], q[:, :hc], a[:, :hc - 1], a[:, hc - 1:hc - 1 + k])  # (1, K, V, N, D)
            row.append((f"{label}\n({part} dims)" if part else label,
                        dec(tokens(zp[:, -1, v])).permute(0, 2, 3, 1)[0].numpy()))
        rows.append(row)
    fig, axes = plt.subplots(n, len(rows[0]) + 1, figsize=(2 * (len(rows[0]) + 1), 2.1 * n), squeeze=False)
    for i, row in enumerate(rows):
        axes[i][0].imshow(pics["images"][i, hc - 1, v].numpy())  # the shared boundary frame
        axes[i][0].set_ylabel(f"sibling {i}", fontsize=8)
        for j, (label, pic) in enumerate(row, start=1):
            axes[i][j].imshow(np.clip(pic, 0, 255 if pic.dtype == np.uint8 else 1))
            if i == 0:
                axes[i][j].set_title(label if label.startswith("real") else f"{label}: predicted", fontsize=9)
        if i == 0:
            axes[i][0].set_title("at the boundary", fontsize=9)
    for ax in axes.flat:
        ax.set_xticks([]), ax.set_yticks([])
    fig.suptitle(f"{args.store.name}: validation branch group {args.group}, {args.camera} view, {k * cfg.frameskip} "
                 f"steps into each sibling's chunk", fontsize=9)
    return save_figure(fig, args.out)


if __name__ == "__main__":
    from wamplan.errors import run_script

    run_script(lambda: print(main()), "wm_sibling_picture")
