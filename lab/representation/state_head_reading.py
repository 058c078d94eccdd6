"""How well a world model's state head (or a ridge probe on its encoder's tokens) reads the pose from the WAM's
predicted views and from the model's own predictions, against the real ones.

(The state head left the core at stop 78, and with ``task-cnn`` the privileged targets this script reads,
``data.readers.state_targets``: it runs at commit 9c6eb5d or earlier, a state head at 04a138b or earlier.)

The pose term of the planning cost (``eval --cost-state-weight``) compares the head's reading of each candidate's
predicted outcome with its reading of the WAM's predicted images at t + H. The head learnt from real frames; this
script measures, at every chunk boundary t of held-out episodes of a WAM policy (a store from `wamplan collect
--source policy`), the head's error against the simulator's truth at t + H, read from the real frame at t + H and from
the WAM's prediction of it made at t, and from the world model's own prediction of it (the executed chunk
rolled out from the real history at t, as the planner rolls out each candidate):

    python lab/representation/state_head_reading.py --store STORE --wam checkpoints/mini/tinywam \\
        --wm checkpoints/candidates/s56_state_ridge [--json OUT.json]

``--probe STORE2`` reads with a ridge probe instead of a head: fitted on the tokens of all views of every stored
frame of STORE2 (other episodes than STORE's), in the world model's own encoder; a model without a
head is read this way, so models on different encoders can be compared on what their predictions carry.

Prints the root mean square error (mm) per quantity (``wamplan.data.readers.STATE_QUANTITIES``) of both readings,
and of the target the pose term aims at: the head on the WAM's view minus the head on the real view.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from wamplan.api import load_wam, planned_policy
from wamplan.data.readers import STATE_QUANTITIES, STATE_UNIT_MM, state_targets
from wamplan.data.store import EpisodeStore
from wamplan.encoders.probe import ProbeConfig, Ridge
from wamplan.envs.spec import Observation
from wamplan.planning.dynamics import PlanningContext


def ridge_reader(policy, store: str, folds: int = 4):
    """A linear read-out of the privileged state (cm) from ``policy``'s encoder tokens (V, N, D): a ridge fit on
    every stored frame of ``store``, its strength chosen by cross-validation over whole episodes
    (``encoders.probe``'s grid). z (B, V, N, D) -> (B, S)."""
    zs, ss, ep = [], [], []
    st = EpisodeStore(store)
    for e, path in enumerate(st.episode_paths()):
        with st.open_episode(path) as f:
            steps = [int(s) for s in f["image_steps"][:]]
            with torch.inference_mode():
                zs += [policy.encode({c: f[f"images/{c}"][k] for c in policy.cameras}) for k in range(len(steps))]
            ss.append(state_targets(f, steps, str(path)))
            ep += [e] * len(steps)
    x = torch.stack(zs).flatten(1).double().numpy()  # (n, V N D)
    y, ep = np.concatenate(ss).astype(np.float64), np.asarray(ep)  # (n, S), (n,)
    alphas = ProbeConfig().alphas
    err = np.zeros(len(alphas))
    for j in range(folds):
        held = ep % folds == j
        pred = Ridge(x[~held], y[~held]).predict(x[held], alphas)  # (A, m, S)
        err += np.square(pred - y[held]).sum(axis=(1, 2))
    alpha = alphas[int(np.argmin(err))]
    ridge = Ridge(x, y)
    return lambda z: torch.from_numpy(ridge.predict(z.flatten(1).double().numpy(), [alpha])[0]).float()


def readings(store: str, wam_path: str, wm_path: str, probe: str | None = None) -> dict[str, np.ndarray]:
    """(B, S) arrays in mm: ``truth``, ``real`` (the head on the real frame at t + H), ``wam`` (on the WAM's
    prediction of it, made at t), ``model`` (on the world model's prediction of it under the executed chunk), over
    every boundary t of the store's episodes whose history frames and frame at t + H are stored."""
    wam = load_wam(wam_path, device="cpu")
    policy = planned_policy(wam, wm_path, device="cpu")
    read = getattr(policy.dynamics, "read_state", None) if probe is None else ridge_reader(policy, probe)
    if read is None:  # the state head left the core at stop 78 (lab/README.md)
        raise SystemExit(f"{wm_path}: a state head is read at commit 04a138b or earlier (the state head left "
                         f"wamplan); here, pass --probe STORE")
    H, cams, dyn = wam.chunk_length, policy.cameras, policy.dynamics
    hist = [-i * dyn.frameskip for i in range(dyn.context - 1, -1, -1)]  # history offsets, oldest first
    out: dict[str, list[np.ndarray]] = {"truth": [], "real": [], "wam": [], "model": []}
    st = EpisodeStore(store)
    for path in st.episode_paths():
        with st.open_episode(path) as f:
            steps = [int(s) for s in f["image_steps"][:]]
            at = {s: k for k, s in enumerate(steps)}
            acts = torch.from_numpy(f["actions"][:].astype(np.float32))  # (T, A)
            for t in [s for s in steps if s % H == 0 and s + H in at and all(s + o in at for o in hist)]:
                views = {c: f[f"images/{c}"][at[t]] for c in cams}  # (H, W, 3) each
                obs = Observation(step=t, images=views, proprio=f["proprio"][t])
                predicted = wam.predict(obs, wam.default_instruction).images
                real = {c: f[f"images/{c}"][at[t + H]] for c in cams}
                with torch.inference_mode():
                    out["wam"].append(read(policy.encode(predicted)[None])[0].numpy())
                    out["real"].append(read(policy.encode(real)[None])[0].numpy())
                    z = torch.stack([policy.encode({c: f[f"images/{c}"][at[t + o]] for c in cams}) for o in hist])
                    q = torch.from_numpy(f["proprio"][[t + o for o in hist]].astype(np.float32))  # (Tc, P)
                    a = acts[t + hist[0]:t].reshape(len(hist) - 1, -1)  # (Tc-1, Δ·A)
                    dyn.prepare(PlanningContext(z, q, a))
                    out["model"].append(read(dyn.terminal(acts[t:t + H][None]))[0].numpy())
                out["truth"].append(state_targets(f, [t + H], str(path))[0])
    return {k: np.stack(v) * STATE_UNIT_MM for k, v in out.items()}  # (B, S) mm


def rms(x: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean(np.square(x), axis=0))  # (S,)


def main() -> None:
    p = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    p.add_argument("--store", required=True, help="episodes of a WAM policy (`wamplan collect --source policy`)")
    p.add_argument("--wam", required=True, help="the WAM checkpoint whose predictions are read")
    p.add_argument("--wm", required=True, help="a world model with a state head (`wm train --state-weight`)")
    p.add_argument("--probe", default=None, help="read with a ridge probe fitted on this store's frames instead of "
                                                 "the model's state head")
    p.add_argument("--json", default="", help="also write the figures to this file")
    args = p.parse_args()
    r = readings(args.store, args.wam, args.wm, args.probe)
    rows = {"head on the real frame vs truth": rms(r["real"] - r["truth"]),
            "head on the WAM's view vs truth": rms(r["wam"] - r["truth"]),
            "head on the WAM's view vs on the real frame": rms(r["wam"] - r["real"]),
            "head on the model's prediction vs truth": rms(r["model"] - r["truth"]),
            "head on the model's prediction vs on the real frame": rms(r["model"] - r["real"]),
            "truth's spread (predicting its mean)": rms(r["truth"] - r["truth"].mean(0))}
    print(f"{len(r['truth'])} boundaries; root mean square error in mm")
    print(f"{'':46s}" + "".join(f"{q:>14s}" for q in STATE_QUANTITIES) + f"{'all':>8s}")
    for name, v in rows.items():
        print(f"{name:46s}" + "".join(f"{x:14.1f}" for x in v) + f"{np.sqrt(np.mean(v ** 2)):8.1f}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"boundaries": len(r["truth"]), "quantities": list(STATE_QUANTITIES),
                       **{k: v.tolist() for k, v in rows.items()}}, fh, indent=1)


if __name__ == "__main__":
    from wamplan.errors import run_script

    run_script(main, "state_head_reading")
