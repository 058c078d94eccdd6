"""How far world models move their prediction of a chunk's end with the chunk: sibling-sized changes against drastic ones.

    python lab/wm-variants/wm_action_response.py STORE shipped=checkpoints/stack-cube/wm_augmented new=RUN [--split val]

For every branch group of STORE (``wamplan collect --branches``; the held-out split by default), each model rolls
the siblings' chunks out from their shared context, and the chunk's last predicted frame (visual tokens) is compared:

* ``pred_spread`` / ``true_spread``: the siblings' mean squared deviation from their group mean, predicted and real
  (the model's share of how much sibling chunks' outcomes differ: what a planner's ranking has to go on);
* ``zeroed`` and ``negated``: the mean squared change of the prediction when the chunk's actions are set to zero or
  negated (a drastic change: whether the model reads the actions at all);
* ``chunk_abs`` and ``sibling_abs``: the mean absolute action, and the siblings' mean absolute deviation from their
  group's mean chunk (normalised action units), the scale of the two kinds of change.

A model that reads the actions but predicts a small share of the siblings' spread is blind at the planner's scale.
"""

from __future__ import annotations

import argparse

import torch

from wamplan.errors import UserError, run_script

FIGURES = ("pred_spread", "true_spread", "zeroed", "negated", "chunk_abs", "sibling_abs")


@torch.no_grad()
def action_response(model, groups, horizon: int) -> dict[str, float]:
    """The figures of the module docstring for ``model`` over ``groups`` (a ``BranchGroups`` in its encoder's
    features), each a mean over the groups; ``groups`` = their number."""
    from wamplan.worldmodel.losses import sibling_futures

    h = model.cfg.context
    sums = dict.fromkeys(FIGURES, 0.0)
    for i in range(len(groups)):
        batch = {k: groups[i][k][None] for k in ("z", "q", "a")}  # one group: each (1, G, T, ...)
        chunk = batch["a"][..., h - 1:h - 1 + horizon, :].float()  # (1, G, K, Δ·A): the siblings' chunks

        def end(actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            """The predicted and the true last frames (G, V, N, D) with the chunks replaced by ``actions``."""
            a = batch["a"].float().clone()
            a[..., h - 1:h - 1 + horizon, :] = actions
            zp, zt, _ = sibling_futures(model, {**batch, "a": a}, horizon)  # (1, G, K, V, N, D) each
            return zp[0, :, -1].float(), zt[0, :, -1].float()

        pred, true = end(chunk)
        sums["pred_spread"] += float((pred - pred.mean(0)).pow(2).mean())
        sums["true_spread"] += float((true - true.mean(0)).pow(2).mean())
        sums["zeroed"] += float((end(torch.zeros_like(chunk))[0] - pred).pow(2).mean())
        sums["negated"] += float((end(-chunk)[0] - pred).pow(2).mean())
        sums["chunk_abs"] += float(chunk.abs().mean())
        sums["sibling_abs"] += float((chunk - chunk.mean(1, keepdim=True)).abs().mean())
    n = len(groups)
    return {"groups": n, **{k: v / max(n, 1) for k, v in sums.items()}}


def main() -> None:
    p = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    p.add_argument("store", help="an episode store with counterfactual branches")
    p.add_argument("models", nargs="+", metavar="LABEL=CKPT", help="world-model checkpoints to compare")
    p.add_argument("--split", default="val", choices=("train", "val", "all"), help="the groups scored (default: val)")
    p.add_argument("--horizon", type=int, default=4, help="frames into the chunk (chunk / frameskip; default: 4)")
    args = p.parse_args()
    from wamplan.data.readers import BranchGroups
    from wamplan.worldmodel.stores import labelled_models

    for label, model, features in labelled_models(args.models, [args.store]):
        groups = BranchGroups([args.store], model.cfg.frameskip, model.cfg.context, args.horizon, split=args.split,
                              features=features)
        if not len(groups):
            raise UserError(f"{args.store} holds no branch groups in its {args.split} split: collect with "
                            f"`wamplan collect --branches N` or pass --split all")
        r = action_response(model, groups, args.horizon)
        print(f"{label}: {r['groups']} groups; " + ", ".join(f"{k} {r[k]:.4f}" for k in FIGURES)
              + f"; predicted share of the siblings' spread {r['pred_spread'] / max(r['true_spread'], 1e-12):.0%}")


if __name__ == "__main__":
    run_script(main, "wm_action_response")
