"""How predictable the wrist view is from geometry alone: the frame at t warped by the camera's motion over the table
plane, against the world model's prediction and against copying the frame (a diagnostic of a kinematic prior).

At every chunk boundary t of a WAM's open-loop episodes, the wrist view at t + H is predicted three ways and each
prediction is encoded with the world model's encoder and compared, token by token, with the real frame's tokens:

- copy: the frame at t;
- warp: the frame at t re-projected through the table plane (z = 0) from the camera's pose at t to its pose at t + H
  (the poses are the simulator's: an upper bound of a warp driven by the commanded motion), the robot's own pixels
  (rigid to the wrist camera) and the held cube (once grasped) kept where they were;
- model: the world model's prediction of the executed chunk from the real history (as the planner rolls out each
  candidate).

    python lab/representation/wrist_warp_probe.py --wam checkpoints/mini/tinywam --wm checkpoints/mini/wm_augmented \\
        --seeds 3016-3019 [--picture OUT.png]

Prints the mean squared token error of each (the wrist view; lower is better) and, per boundary, which is closer.

With ``--candidates N`` it also ranks: at each boundary the WAM's chunk and N - 1 samples around it (noise
``--sigma``) are each run in the simulator from the boundary's snapshot, and the wrist-view cost against the WAM's
predicted wrist picture is computed from the real outcome (the truth), from the world model's prediction, and from
the frame at t warped to each candidate's real camera pose; it prints the median Spearman of the model's and the
warp's costs against the truth.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from wamplan.config import int_list
from wamplan.envs.config import EnvConfig
from wamplan.envs.core import TaskEnv
from wamplan.planning.dynamics import LearnedDynamics, PlanningContext
from wamplan.policies.rollout import run_episode
from wamplan.wam import WAMPolicy, load_wam
from wamplan.worldmodel.load import load_world_model

CAM = "wrist"


def camera_state(env: TaskEnv) -> dict:
    """The wrist camera's intrinsics K (3, 3), world -> camera extrinsics E (3, 4) (OpenCV axes), and its picture's
    segmentation: which pixels are the robot's, which the cube's (H, W) bool each."""
    base = env.base
    cam = base.scene.sensors[CAM]
    base.scene.update_render(update_sensors=True, update_human_render_cameras=False)
    cam.capture()
    obs = cam.get_obs(rgb=True, depth=False, position=False, segmentation=True)
    seg = obs["segmentation"][0, ..., 0].numpy()
    ids = base.segmentation_id_map
    robot = [i for i, o in ids.items() if type(o).__name__ == "Link"]
    cube = [i for i, o in ids.items() if o.name == "cube"]
    params = cam.get_params()
    return {"K": params["intrinsic_cv"][0].numpy().astype(np.float64),
            "E": params["extrinsic_cv"][0].numpy().astype(np.float64),
            "rgb": obs["rgb"][0].numpy(), "robot": np.isin(seg, robot), "cube": np.isin(seg, cube),
            "grasped": bool(base.evaluate()["grasped"][0])}


def warp(a: dict, b: dict) -> np.ndarray:
    """Frame ``a``'s picture seen from ``b``'s camera pose through the plane z = 0; (H, W, 3) uint8. Pixels whose ray
    misses the plane or lands outside ``a`` keep ``a``'s; the robot (and the cube, if grasped at ``a``) keep ``a``'s."""
    img = a["rgb"]
    h, w = img.shape[:2]
    v, u = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5  # pixel centres
    rays = np.linalg.inv(b["K"]) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])  # (3, HW) in b's camera
    rb, tb = b["E"][:, :3], b["E"][:, 3]
    centre = -rb.T @ tb  # (3,) b's camera centre in the world
    dirs = rb.T @ rays  # (3, HW) world directions
    s = -centre[2] / dirs[2]  # (HW,) to z = 0
    points = centre[:, None] + s * dirs  # (3, HW)
    pa = a["K"] @ (a["E"][:, :3] @ points + a["E"][:, 3:])  # (3, HW) in a's pixels
    ua, va = pa[0] / pa[2], pa[1] / pa[2]
    ok = (s > 0) & (pa[2] > 0) & (ua >= 0) & (ua < w) & (va >= 0) & (va < h)
    grid = torch.from_numpy(np.stack([ua / w * 2 - 1, va / h * 2 - 1], -1).reshape(1, h, w, 2)).float()
    src = torch.from_numpy(img).permute(2, 0, 1)[None].float()  # (1, 3, H, W)
    out = torch.nn.functional.grid_sample(src, grid, align_corners=False)[0].permute(1, 2, 0).numpy()
    out = np.where(ok.reshape(h, w, 1), out, img)
    keep = a["robot"] | (a["cube"] if a["grasped"] else False)
    out = np.where(keep[..., None], img, out)
    return out.round().clip(0, 255).astype(np.uint8)


def rank_candidates(env: TaskEnv, snap, start: dict, chunk: np.ndarray, target: torch.Tensor, model_of, enc,
                    n: int, sigma: float, rng: np.random.Generator) -> tuple[float, float]:
    """Spearman of the model's and of the warp's wrist costs against the simulator's, over the WAM's ``chunk`` (H, A)
    and n - 1 noisy copies run from ``snap``; ``model_of(cands (n, H, A)) -> (n, N, D)`` wrist tokens."""
    from scipy.stats import spearmanr

    cands = np.concatenate([chunk[None], np.clip(chunk[None] + sigma * rng.standard_normal((n - 1, *chunk.shape)),
                                                 -1, 1)]).astype(np.float32)  # (n, H, A)
    model = (model_of(torch.from_numpy(cands)) - target).square().mean(dim=(1, 2)).numpy()  # (n,)
    true, warped = np.zeros(n), np.zeros(n)
    for i, cand in enumerate(cands):
        env.restore(snap)
        for a in cand:
            env.step(a)
        end = camera_state(env)
        true[i] = float((enc(end["rgb"]) - target).square().mean())
        warped[i] = float((enc(warp(start, end)) - target).square().mean())
    return float(spearmanr(model, true)[0]), float(spearmanr(warped, true)[0])


def probe(wam_path: str, wm_path: str, seeds: list[int], candidates: int = 0, sigma: float = 0.1) -> dict:
    wam = load_wam(wam_path, device="cpu")
    predictor, encoder = load_world_model(wm_path)
    dyn = LearnedDynamics(predictor)
    cams = predictor.cameras or wam.task.cameras
    vi = cams.index(CAM)
    step_every = dyn.frameskip
    hist = [-i * step_every for i in range(dyn.context - 1, -1, -1)]  # offsets, oldest first
    env = TaskEnv(EnvConfig(task=wam.task.name, camera_size=224))
    policy = WAMPolicy(wam)
    H = policy.chunk_length
    out: dict[str, list] = {"copy": [], "warp": [], "model": [], "pictures": [], "rank_model": [], "rank_warp": []}
    rng = np.random.default_rng(0)
    for seed in seeds:
        frames, states, proprio, actions, snaps, outputs = {}, {}, {}, [], {}, {}

        def keep(env: TaskEnv, obs, action) -> None:
            if action is not None:
                actions.append(np.asarray(action, np.float32))
            proprio[obs.step] = obs.proprio.astype(np.float32)
            if obs.step % step_every == 0:
                frames[obs.step] = env.render(tuple(cams))
            if obs.step % H == 0:
                states[obs.step] = camera_state(env)
                if candidates:
                    snaps[obs.step] = env.snapshot()
                if obs.step:  # the WAM's proposal made at the last boundary, before the policy asks for the next
                    outputs[obs.step - H] = policy.last_output

        run_episode(env, policy, seed, on_obs=keep)
        acts = torch.from_numpy(np.stack(actions))  # (T, A)
        for t in sorted(states):
            if t + H not in states or t + hist[0] < 0:
                continue
            with torch.no_grad():
                enc = lambda pic: encoder.encode(pic)[0].float()  # noqa: E731  (H, W, 3) -> (N, D)
                real = enc(states[t + H]["rgb"])
                z = torch.stack([torch.stack([encoder.encode(frames[t + o][c])[0] for c in cams]) for o in hist])
                q = torch.from_numpy(np.stack([proprio[t + o] for o in hist]))  # (Tc, P)
                a = acts[t + hist[0]:t].reshape(len(hist) - 1, -1)  # (Tc-1, Δ·A)
                dyn.prepare(PlanningContext(z.float(), q, a))
                model = dyn.terminal(acts[t:t + H][None])[0, vi].float()  # (N, D)
                warped = warp(states[t], states[t + H])
                for name, pred in (("copy", enc(states[t]["rgb"])), ("warp", enc(warped)), ("model", model)):
                    out[name].append(float((pred - real).square().mean()))
                if candidates and t in outputs:
                    target = enc(outputs[t].images[CAM])
                    rm, rw = rank_candidates(env, snaps[t], states[t], outputs[t].actions, target,
                                             lambda c: dyn.terminal(c)[:, vi].float(), enc, candidates, sigma, rng)
                    out["rank_model"].append(rm)
                    out["rank_warp"].append(rw)
            out["pictures"].append((states[t]["rgb"], warped, states[t + H]["rgb"]))
        print(f"seed {seed}: {len(out['copy'])} boundaries so far", flush=True)
    env.close()
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    p.add_argument("--wam", required=True)
    p.add_argument("--wm", required=True)
    p.add_argument("--seeds", required=True)
    p.add_argument("--picture", default="")
    p.add_argument("--candidates", type=int, default=0, help="also rank N candidates a boundary (0: off)")
    p.add_argument("--sigma", type=float, default=0.1)
    args = p.parse_args()
    r = probe(args.wam, args.wm, int_list(args.seeds, "--seeds"), args.candidates, args.sigma)
    c, w, m = (np.array(r[k]) for k in ("copy", "warp", "model"))
    print(f"{len(c)} boundaries; the wrist view's token error at t + H (mean squared, mean ± SE):")
    for name, x in (("copy the frame at t", c), ("warp it through the table plane", w), ("the world model", m)):
        print(f"  {name:34s} {x.mean():.4f} ± {x.std(ddof=1) / np.sqrt(len(x)):.4f}")
    print(f"  warp beats the model at {np.mean(w < m):.0%} of boundaries, copying at {np.mean(w < c):.0%}")
    if r["rank_model"]:
        rm, rw = np.array(r["rank_model"]), np.array(r["rank_warp"])
        q = lambda x: f"{np.median(x):.2f} [{np.quantile(x, 0.25):.2f}, {np.quantile(x, 0.75):.2f}]"  # noqa: E731
        print(f"{len(rm)} boundaries ranked ({args.candidates} candidates): the wrist cost's Spearman with the "
              f"simulator's, median [IQR]: the world model {q(rm)}, the warp {q(rw)}; paired warp - model "
              f"{np.mean(rw - rm):+.2f} ± {np.std(rw - rm, ddof=1) / np.sqrt(len(rm)):.2f}")
    if args.picture:
        import matplotlib.pyplot as plt

        from wamplan.plot import save_figure

        idx = np.linspace(0, len(r["pictures"]) - 1, 4).round().astype(int)
        fig, axes = plt.subplots(4, 3, figsize=(6, 8), squeeze=False)
        for row, i in enumerate(idx):
            for k, title in enumerate(("wrist at t", "warped to t + H", "real at t + H")):
                axes[row, k].imshow(r["pictures"][i][k])
                axes[row, k].set_title(title, fontsize=8)
                axes[row, k].axis("off")
        save_figure(fig, args.picture, dpi=70)


if __name__ == "__main__":
    from wamplan.errors import run_script

    run_script(main, "wrist_warp_probe")
