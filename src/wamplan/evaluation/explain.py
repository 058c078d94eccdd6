"""``wamplan explain``'s run: condition 7 up to one chunk boundary, that chunk planned, and the WAM's chunk and the
plan each executed from the same snapshot, collected as a :class:`~wamplan.evaluation.mechanism.Mechanism` (the
picture is :func:`~wamplan.evaluation.mechanism.mechanism_figure`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from wamplan.errors import UserError
from wamplan.evaluation.mechanism import Mechanism, model_pictures


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
    pics, _ = model_pictures(policy, dec, chunks)  # "wam" / "plan" -> (V, S, S, 3)
    cands = torch.as_tensor(np.stack(list(chunks.values())), device=policy.device)  # (2, H, A)
    covered = policy.dynamics.covered(policy.chunk)
    model_cost = policy.objective(target)(policy.clip(cands[:, :covered]))  # (2,) what the planner minimised
    cams = policy.cameras
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
                     model=pics, real=real,
                     model_cost={k: float(model_cost[i]) for i, k in enumerate(chunks)}, true_cost=true_cost,
                     cube_xy_mm=xy or None, cameras=tuple(cams), chunk=policy.chunk)
