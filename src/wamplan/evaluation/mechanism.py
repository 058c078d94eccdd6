"""The mechanism of feedback planning, for one chunk, in one picture (``wamplan explain``).

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
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from wamplan.errors import UserError


@dataclass
class Mechanism:
    step: int
    now: np.ndarray  # (V, H, W, 3) uint8
    target: np.ndarray  # (V, h, w, 3) uint8, the WAM's predicted views at t+H
    model: dict[str, np.ndarray]  # "wam" / "plan" -> (V, S, S, 3) float in [0, 1], decoded predictions
    real: dict[str, np.ndarray]  # "wam" / "plan" -> (V, H, W, 3) uint8 after executing the chunk
    model_cost: dict[str, float]
    true_cost: dict[str, float]
    cube_xy_mm: dict[str, float] | None  # the cube's xy distance to the hole axis after each chunk (None: no cube)
    cameras: tuple[str, ...]  # the V views, in order
    chunk: int  # H: the target is at step + chunk


@torch.no_grad()  # not inference mode: the env built here must hold ordinary tensors
def explain_chunk(cfg, decoder: str | Path, seed: int, chunk_index: int) -> Mechanism:
    """Run condition 7 of ``cfg`` (an ``EvalConfig``) on ``seed`` up to chunk ``chunk_index`` (>= 1), plan that
    chunk, and compare the WAM's chunk with the plan in the model and in the simulator."""
    from wamplan.evaluation.runner import EvalWorker
    from wamplan.wam.once import OnceWAM
    from wamplan.policies.rollout import run_episode
    from wamplan.worldmodel.decoder import load_decoder

    if chunk_index < 1:
        raise UserError(f"--chunk {chunk_index}: chunk 0 always runs open loop; pick a chunk index >= 1")
    worker = EvalWorker(cfg)
    policy = worker.policy(7)
    policy.wam = policy.target_wam = once = OnceWAM(policy.wam)  # one query per step, kept for the picture
    once.new_episode()
    env, t = worker.env, chunk_index * policy.chunk
    r = run_episode(env, policy, seed, max_steps=t)
    if r.length < t:
        raise UserError(f"seed {seed} ended ({r.outcome}) at step {r.length}, before chunk {chunk_index}; pick an "
                        f"earlier --chunk")
    obs = env.observe(with_images=True)
    decision = policy.plan_chunk(obs)
    target_views = once.last.images
    target = decision.target if decision.target is not None else policy.encode(target_views)  # (V, N, D)
    dec = load_decoder(decoder, encoder=policy.encoder, task=cfg.env.spec.name)
    chunks = {"wam": decision.seed, "plan": decision.executed}  # (H, A) each
    cands = torch.as_tensor(np.stack(list(chunks.values())), device=policy.device)  # (2, H, A)
    covered = policy.dynamics.covered(policy.chunk)
    z = policy.dynamics.terminal(policy.clip(cands[:, :covered]))  # (2, V, N, D), for the pictures
    model_cost = policy.objective(target)(policy.clip(cands[:, :covered]))  # (2,) what the planner minimised
    pics = dec(z.flatten(0, 1).float().to(next(dec.parameters()).device))  # (2V, 3, S, S)
    cams = policy.cameras
    pics = pics.permute(0, 2, 3, 1).reshape(2, len(cams), *pics.shape[2:], 3).cpu().numpy()
    snap = env.snapshot()
    real, true_cost, xy = {}, {}, {}
    for k, acts in chunks.items():
        env.restore(snap)
        for a in acts:
            env.step(a)
        views = env.render(cams)
        real[k] = np.stack([views[c] for c in cams])
        true_cost[k] = float(policy.cost(policy.encode(views)[None], target)[0])
        s = env.privileged_state()
        if "cube_pose" in s and "hole_pos" in s:
            xy[k] = float(np.linalg.norm(s["cube_pose"][:2] - s["hole_pos"][:2]) * 1000)
    env.restore(snap)
    return Mechanism(step=t, now=np.stack([obs.images[c] for c in cams]),
                     target=np.stack([target_views[c] for c in cams]),
                     model={k: pics[i] for i, k in enumerate(chunks)}, real=real,
                     model_cost={k: float(model_cost[i]) for i, k in enumerate(chunks)}, true_cost=true_cost,
                     cube_xy_mm=xy or None, cameras=tuple(cams), chunk=policy.chunk)


def mechanism_figure(m: Mechanism, out: str | Path, title: str = "") -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from wamplan.plot import save_figure

    cube = {k: f", cube {m.cube_xy_mm[k]:.1f} mm" if m.cube_xy_mm else "" for k in ("wam", "plan")}
    cols = [(f"now (step {m.step})", m.now), (f"WAM's target (step {m.step + m.chunk})", m.target),
            (f"model, WAM's chunk\ncost {m.model_cost['wam']:.3f}", m.model["wam"]),
            (f"model, plan\ncost {m.model_cost['plan']:.3f}", m.model["plan"]),
            (f"real, WAM's chunk\ncost {m.true_cost['wam']:.3f}{cube['wam']}", m.real["wam"]),
            (f"real, plan\ncost {m.true_cost['plan']:.3f}{cube['plan']}", m.real["plan"])]
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
