"""Does a world model's error at one chunk boundary predict its error one chunk later? A probe of test-time correction.

    python lab/wm-variants/wm_error_persistence.py STORE shipped=checkpoints/mini/wm_augmented [new=RUN] [--split val]

At a chunk boundary the robot has just seen how the last chunk really ended, so the model's error on it is known.
If errors persisted from chunk to chunk, a planner could subtract it from every candidate's prediction. For each
pair of windows of one episode of STORE a chunk apart (``horizon`` frames at the model's Δ), the model predicts each
window's last frame from its context and the executed actions, and the script reports, over all pairs:

* ``left_L``: what is left of the later error after subtracting L times the earlier one, as a share of the later
  error (squared, summed over the pairs): below 1 the correction helps, above 1 it adds noise;
* ``cosine``: the median cosine between the two errors (0: unrelated);
* ``error_share``: the later error over the true change of the last frame from the context's last frame (both
  squared): how large the errors are against what happens in a chunk.
"""

from __future__ import annotations

import argparse

import torch

from wamplan.errors import UserError, run_script

LAMBDAS = (0.25, 0.5, 1.0)


def chunk_pairs(windows, horizon: int) -> list[tuple[int, int]]:
    """Index pairs (i, j) of ``windows`` (a ``WorldModelWindows``): window j starts ``horizon`` frames after window
    i, in the same episode, so j's context ends where i's prediction does."""
    at = {item: j for j, item in enumerate(windows.items)}
    pairs = []
    for i, (e, k) in enumerate(windows.items):
        j = at.get((e, k + horizon * (windows.frameskip // windows.episodes[e].image_every)))
        if j is not None:
            pairs.append((i, j))
    return pairs


@torch.no_grad()
def error_persistence(model, windows, horizon: int, batch_size: int = 32) -> dict[str, float]:
    """The figures of the module docstring for ``model`` over ``windows`` (in its encoder's features)."""
    from torch.utils.data import default_collate

    from wamplan.worldmodel.losses import split_windows

    def last_frame(idx: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
        """The error of the predicted last frame and the true change to it, each (B, V·N·D)."""
        (zc, qc, ac), a_future, (zt, _) = split_windows(model, default_collate([windows[i] for i in idx]), horizon)
        zp, _ = model.rollout(zc, qc, ac, a_future)  # (B, K, V, N, D)
        return (zt[:, -1] - zp[:, -1]).flatten(1).float(), (zt[:, -1] - zc[:, -1]).flatten(1).float()

    pairs = chunk_pairs(windows, horizon)
    if not pairs:
        return {"pairs": 0}
    used = sorted({i for pair in pairs for i in pair})  # a window inside a run of chunks is in two pairs: rolled once
    parts = [last_frame(used[s:s + batch_size]) for s in range(0, len(used), batch_size)]
    row = {w: r for r, w in enumerate(used)}
    error, change = (torch.cat(x) for x in zip(*parts))  # (W, V·N·D) each, in the order of ``used``
    before, after = error[[row[i] for i, _ in pairs]], error[[row[j] for _, j in pairs]]  # (P, V·N·D) each
    later = float(after.pow(2).sum())
    left = {lam: float((after - lam * before).pow(2).sum()) / max(later, 1e-12) for lam in LAMBDAS}
    return {"pairs": len(pairs), **{f"left_{lam:g}": v for lam, v in left.items()},
            "cosine": float(torch.nn.functional.cosine_similarity(before, after, dim=1).median()),
            "error_share": later / max(float(change[[row[j] for _, j in pairs]].pow(2).sum()), 1e-12)}

def main() -> None:
    p = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    p.add_argument("store", help="an episode store (episodes longer than two chunks)")
    p.add_argument("models", nargs="+", metavar="LABEL=CKPT", help="world-model checkpoints to compare")
    p.add_argument("--split", default="val", choices=("train", "val", "all"), help="the episodes scored (default: val)")
    p.add_argument("--horizon", type=int, default=4, help="frames in a chunk (chunk / frameskip; default: 4)")
    args = p.parse_args()
    from wamplan.data.readers import WorldModelWindows
    from wamplan.worldmodel.stores import labelled_models

    for label, model, features in labelled_models(args.models, [args.store]):
        windows = WorldModelWindows([args.store], model.cfg.frameskip, model.cfg.context, args.horizon,
                                    split=args.split, features=features)
        r = error_persistence(model, windows, args.horizon)
        if not r["pairs"]:
            raise UserError(f"{args.store} holds no two windows a chunk apart in its {args.split} split: it needs "
                            f"episodes of at least {(model.cfg.context + 2 * args.horizon) * model.cfg.frameskip} "
                            f"steps, or pass --split all")
        print(f"{label}: {r['pairs']} pairs; " + ", ".join(f"left_{lam:g} {r[f'left_{lam:g}']:.3f}" for lam in LAMBDAS)
              + f"; cosine {r['cosine']:.2f}; error_share {r['error_share']:.2f}")


if __name__ == "__main__":
    run_script(main, "wm_error_persistence")
