"""The mechanism of feedback planning, for one chunk, in one picture (``wamplan explain``; the run that fills it is
:func:`wamplan.evaluation.explain.explain_chunk`).

At chunk boundary t of a condition-7 episode (the WAM with planning in the world model), per view:

    now (t) | WAM's target (t+H) | model under the WAM's chunk | model under the plan | real after the WAM's
    chunk | real after the plan

The model's columns are its predicted terminal embeddings decoded to pixels (the decoder is only for
looking; planning never uses it); the real columns are rendered after executing each chunk from the same
snapshot. Costs are the planning cost (eq. 3) against the WAM's target: the model's (what the planner minimised)
and the true one (the rendered frame encoded by the same encoder), so the picture says whether the plan
the model preferred is also better in the simulator, and where the model's picture differs from reality.
The views are the planned policy's (its world model's cameras, in order); where the task's privileged state
has the cube and the hole (the cube task), each real column also says how far the cube ended from the hole's
axis.

The same columns, one picture per chunk boundary of a whole episode, are an evaluation's plan video
(:func:`mechanism_frame`, ``wamplan.evaluation.filming``): there only the chunk that ran is real.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch



@dataclass
class Mechanism:
    step: int
    now: np.ndarray  # (V, H, W, 3) uint8
    target: np.ndarray  # (V, h, w, 3) uint8, the WAM's predicted views at t+H
    model: dict[str, np.ndarray]  # "wam" / "plan" -> (V, S, S, 3) float in [0, 1], decoded predictions ({}: none)
    real: dict[str, np.ndarray]  # "wam" / "plan" -> (V, H, W, 3) uint8 after executing the chunk (those simulated)
    model_cost: dict[str, float]
    true_cost: dict[str, float]
    cube_xy_mm: dict[str, float] | None  # the cube's xy distance to the hole axis after each chunk (None: no cube)
    cameras: tuple[str, ...]  # the V views, in order
    chunk: int  # H: the target is at step + chunk
    reached: int | None = None  # the step of the real views (None: step + chunk)


@torch.no_grad()
def model_pictures(policy, decoder, chunks: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], torch.Tensor]:
    """The planned ``policy``'s world model's predicted views at the end of each chunk (name -> (H, A) actions),
    decoded to pixels by ``decoder`` -> (name -> (V, S, S, 3) float in [0, 1], the predicted embeddings
    (C, V, N, D) in ``chunks``' order). Its dynamics must be prepared for the
    current boundary (as the policy leaves it after planning) and learned (a simulator backend would step the env)."""
    cands = torch.as_tensor(np.stack(list(chunks.values())), device=policy.device)  # (C, H, A)
    covered = policy.dynamics.covered(policy.chunk)
    z = policy.dynamics.terminal(policy.clip(cands[:, :covered]))  # (C, V, N, D)
    pics = decoder(z.flatten(0, 1).float().to(next(decoder.parameters()).device))  # (C·V, 3, S, S)
    pics = pics.permute(0, 2, 3, 1).reshape(len(chunks), z.shape[1], *pics.shape[2:], 3).cpu().numpy()
    return {k: pics[i] for i, k in enumerate(chunks)}, z  # (V, S, S, 3) each


def columns(m: Mechanism) -> list[tuple[str, np.ndarray | None]]:
    """The picture's columns, left to right, as (label, (V, h, w, 3) views): now, the WAM's target, the model under
    the WAM's chunk and under the plan, the real views after each chunk; a column ``m`` lacks (no decoder, a chunk
    not simulated) is left out, a cost or cube distance it lacks is not written."""
    def said(k: str, kind: str) -> str:
        cost = (m.model_cost if kind == "model" else m.true_cost).get(k)
        cube = f", cube {m.cube_xy_mm[k]:.1f} mm" if kind == "real" and m.cube_xy_mm and k in m.cube_xy_mm else ""
        return ("" if cost is None or cost != cost else f"\ncost {cost:.3f}") + cube

    names = {"wam": "WAM's chunk", "plan": "plan"}
    cols = [(f"now (step {m.step})", m.now), (f"WAM's target (step {m.step + m.chunk})", m.target)]
    cols += [(f"model, {names[k]}{said(k, 'model')}", m.model[k]) for k in ("wam", "plan") if k in m.model]
    at = f" (step {m.reached})" if m.reached is not None else ""
    cols += [(f"real, {names[k]}{at}{said(k, 'real')}", m.real[k]) for k in ("wam", "plan") if k in m.real]
    return cols


def mechanism_frame(m: Mechanism, size: int, title: str = "") -> np.ndarray:
    """The picture of :func:`mechanism_figure` as one (h, w, 3) uint8 image, views ``size`` px, the cameras as rows
    (a plan video's frame; no matplotlib, a few ms)."""
    from wamplan.envs.media import labelled_grid

    cols = [(label, [None] * len(m.cameras) if views is None else list(views)) for label, views in columns(m)]
    if title:
        cols[0] = (f"{title}\n{cols[0][0]}", cols[0][1])
    return labelled_grid(cols, size, rows=m.cameras, header=30)


def mechanism_figure(m: Mechanism, out: str | Path, title: str = "") -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from wamplan.plot import save_figure

    cols = columns(m)
    cams = m.cameras
    fig, axes = plt.subplots(len(cams), len(cols), figsize=(2.2 * len(cols), 2.3 * len(cams) + 0.6),
                             squeeze=False)
    for j, (label, views) in enumerate(cols):
        for v, cam in enumerate(cams):
            ax = axes[v][j]
            img = views[v]
            ax.imshow(img if img.dtype == np.uint8 else np.clip(img, 0, 1))
            ax.set_xticks([]), ax.set_yticks([])
            if v == 0:
                ax.set_title(label, fontsize=8)
            if j == 0:
                ax.set_ylabel(cam, fontsize=9)
    better = m.true_cost["plan"] < m.true_cost["wam"]
    fig.suptitle((title + "\n" if title else "") + "costs: planning cost (eq. 3) against the WAM's target; model = "
                 "decoded world-model prediction" + ("; cube = xy distance to the hole axis" if m.cube_xy_mm else "")
                 + ". The plan is "
                 f"{'better' if better else 'worse'} than the WAM's chunk in the simulator.", fontsize=8)
    return save_figure(fig, out)
