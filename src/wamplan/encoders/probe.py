"""What an encoder's frozen tokens see: a linear (ridge) probe to the cube's position.

For every stored frame of an episode store the probe reads the encoder's tokens of each view and the
privileged poses, and fits a ridge regression from the flattened tokens to

* ``cube-rel-tcp``: the cube's centre relative to the TCP (what grasping needs), and
* ``cube-rel-hole``: the cube's centre relative to the hole's top centre (what alignment needs; the
  mount is fixed, so this is the cube's world position up to a constant),

per view (the stores' cameras; the cube's front, side, wrist) and for all views concatenated. The split is
by episode: some episodes fit the probe, the others (``val_fraction``, at least one) are held out and scored.
The ridge strength is chosen per target from a grid by grouped cross-validation over the fitting episodes
(folds of whole episodes), then the probe is refit on all fitting episodes. Errors are mean Euclidean
distances in mm on the held-out frames, beside the error of predicting the fitting episodes' mean; the same
errors are also given on the held-out frames whose cube is within ``near_mm`` of the hole axis (the alignment
regime; the baseline there is the mean of the fitting frames in that regime).

A linear read-out is a lower bound on what the tokens carry: a pixel patch is not linear in the position of
the object it shows, so finer pixel grids need not probe better linearly even when a nonlinear model (the
world model) could use them.

    enc = make_encoder("patch-pixels", input_size=64, patch_size=16)
    report = probe_stores(["data/noisy"], [enc])[0]
    print(format_probe(report))

Why ridge in closed form: one SVD of the fitting features serves every ridge strength, the features are
wider than the frames are many (6 144 to 24 576 dims against ~10^3 frames), and the answer does not
depend on an optimiser's settings.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from wamplan.config import check_numbers, field, require
from wamplan.data.alignment import hole_position
from wamplan.data.store import EpisodeStore, StoreError
from wamplan.errors import UserError

TARGETS = ("cube-rel-tcp", "cube-rel-hole")
ALL = "all"  # the views concatenated


@dataclass(frozen=True)
class ProbeConfig:
    val_fraction: float = field(0.25, "fraction of episodes held out for scoring (at least one)")
    folds: int = field(4, "grouped cross-validation folds (whole episodes) for choosing the ridge strength")
    alphas: tuple[float, ...] = field(tuple(10.0 ** (k / 2) for k in range(-12, 5)),
                                      "ridge strengths to try, relative to the mean squared singular value")
    batch_size: int = field(64, "images per encoder call")
    near_mm: float = field(20.0, "also score the held-out frames whose cube is within this xy distance of the hole "
                                 "axis (the alignment regime, where 4 mm matters)")

    def __post_init__(self):
        check_numbers(self)
        require(0 < self.val_fraction < 1, f"val_fraction must be in (0, 1), got {self.val_fraction}")
        require(self.folds >= 2, f"folds must be >= 2, got {self.folds}")
        require(len(self.alphas) > 0 and all(a > 0 for a in self.alphas),
                f"alphas must be positive, got {self.alphas}")
        require(self.near_mm > 0, f"--near-mm must be > 0 (a distance in mm, e.g. 20), got {self.near_mm:g}")


@dataclass
class ProbeData:
    """Features and targets of every stored frame. M = frames over all episodes."""

    features: dict[str, np.ndarray]  # view -> (M, N*D) float32 (``all``: the views concatenated)
    targets: dict[str, np.ndarray]  # target -> (M, 3) float32, metres
    episode: np.ndarray  # (M,) int, index into ``episodes``
    episodes: list[str]  # "<source>:<seed>" per episode, the split's key

    @property
    def views(self) -> tuple[str, ...]:
        """The probed views: each camera, then ``all``."""
        return tuple(self.features)


def _hash01(key: str) -> float:
    return int(hashlib.sha1(key.encode()).hexdigest()[:8], 16) / 0xFFFFFFFF


@torch.inference_mode()
def load_probe_data(stores: Sequence[str | Path], encoders: Sequence[Any], batch_size: int = 64,
                    progress: bool = False) -> list[ProbeData]:
    """Read every episode of ``stores`` (one task's, with the same cameras) once and encode its frames with each
    encoder; one ProbeData per encoder."""
    opened = [EpisodeStore(root) for root in stores]
    cameras = opened[0].cameras if opened else ()
    if other := [str(s.root) for s in opened if s.cameras != cameras]:
        raise UserError(f"the stores {other} have other cameras than {list(cameras)}; probe one task's stores")
    feats: list[dict[str, list[np.ndarray]]] = [{c: [] for c in cameras} for _ in encoders]
    targets: dict[str, list[np.ndarray]] = {t: [] for t in TARGETS}
    episode: list[np.ndarray] = []
    names: list[str] = []
    paths = [(store, p) for store in opened for p in store.episode_paths()]
    if len(paths) < 2:
        raise UserError(f"the probe needs at least 2 episodes (fit and held out); {list(stores)} hold {len(paths)}; "
                        f"collect more with `wamplan collect`")
    for i, (store, path) in enumerate(paths):
        hole = hole_position(store.env)
        with store.open_episode(path) as f:
            if "cube_pose" not in f or "tcp_pose" not in f:
                raise StoreError(f"{path} records no cube or TCP pose; the probe's targets are read from both")
            steps = f["image_steps"][:]  # (K,)
            cube = f["cube_pose"][:][steps, :3]  # (K, 3)
            tcp = f["tcp_pose"][:][steps, :3]  # (K, 3)
            names.append(f"{f.attrs['source']}:{int(f.attrs['seed'])}")
            frames = {c: f["images"][c][:] for c in cameras}  # (K, H, W, 3) uint8 each
        for c in cameras:
            for e, enc in enumerate(encoders):
                z = enc.encode_batched(torch.from_numpy(frames[c]), batch_size)  # (K, N, D) on the CPU
                feats[e][c].append(z.flatten(1).numpy().astype(np.float32))  # (K, N*D)
        targets["cube-rel-tcp"].append(cube - tcp)
        targets["cube-rel-hole"].append(cube - hole[None])
        episode.append(np.full(len(steps), i))
        if progress:
            print(f"  probe: read {i + 1}/{len(paths)} episodes", flush=True)
    tgt = {t: np.concatenate(v).astype(np.float32) for t, v in targets.items()}
    ep = np.concatenate(episode)
    out = []
    for fe in feats:
        views = {c: np.concatenate(fe[c]) for c in cameras}
        views[ALL] = np.concatenate([views[c] for c in cameras], axis=1)  # (M, V N D)
        out.append(ProbeData(views, tgt, ep, names))
    return out


def split_episodes(names: Sequence[str], val_fraction: float) -> np.ndarray:
    """(E,) bool, True for held-out episodes: the ``ceil(val_fraction * E)`` (at least 1, at most E-1) with the
    smallest hash of their "<source>:<seed>", so the split is the same on every machine."""
    order = np.argsort([_hash01(n) for n in names], kind="stable")
    n_val = int(min(max(1, np.ceil(val_fraction * len(names))), len(names) - 1))
    held = np.zeros(len(names), bool)
    held[order[:n_val]] = True
    return held


class Ridge:
    """Ridge regression for many strengths from one SVD. x (M, F), y (M, T); centred on the fitting data."""

    def __init__(self, x: np.ndarray, y: np.ndarray):
        xt = torch.from_numpy(x).double()
        self.mx, self.my = xt.mean(0), torch.from_numpy(y).double().mean(0)  # (F,), (T,)
        xc = xt - self.mx  # (M, F)
        if xc.shape[1] <= xc.shape[0]:
            u, s, vt = torch.linalg.svd(xc, full_matrices=False)  # (M, r), (r,), (r, F)
        else:  # wide features: the (M, M) Gram matrix is cheaper than the SVD, same factors
            w, u = torch.linalg.eigh(xc @ xc.T)  # (M,), (M, M), ascending
            keep = w > w.max().clamp_min(1e-300) * 1e-12
            u, s = u[:, keep], w[keep].sqrt()  # (M, r), (r,)
            vt = (xc.T @ u / s).T  # (r, F)
        self.s, self.vt = s, vt
        self.uy = u.T @ (torch.from_numpy(y).double() - self.my)  # (r, T)
        self.scale = float((s ** 2).mean()) if len(s) else 1.0  # alphas are relative to this

    def predict(self, x: np.ndarray, alphas: Sequence[float]) -> np.ndarray:
        """(len(alphas), M', T) predictions."""
        a = (torch.from_numpy(x).double() - self.mx) @ self.vt.T  # (M', r)
        out = []
        for alpha in alphas:
            d = self.s / (self.s ** 2 + alpha * self.scale)  # (r,)
            out.append(a @ (d[:, None] * self.uy) + self.my)  # (M', T)
        return torch.stack(out).numpy()


def _euclid_mm(pred: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(..., M, 3) vs (M, 3) -> mean Euclidean error in mm over M, shape (...)."""
    return 1000.0 * np.linalg.norm(pred - y, axis=-1).mean(-1)


def _folds(episode: np.ndarray, fit_eps: np.ndarray, k: int) -> list[np.ndarray]:
    """Boolean masks over the fitting frames, one per fold: whole episodes, or two contiguous halves of the
    frames when only one episode fits."""
    ep = episode
    if len(fit_eps) >= 2:
        k = min(k, len(fit_eps))
        return [np.isin(ep, fit_eps[j::k]) for j in range(k)]
    half = np.arange(len(ep)) >= len(ep) // 2
    return [half, ~half]


def probe_arrays(data: ProbeData, config: ProbeConfig | None = None) -> dict[str, Any]:
    """Fit and score the probe on ``data``: rows of {view, target, error_mm, baseline_mm, alpha}."""
    cfg = config or ProbeConfig()
    held = split_episodes(data.episodes, cfg.val_fraction)  # (E,)
    test = held[data.episode]  # (M,)
    fit = ~test
    fit_eps = np.flatnonzero(~held)
    folds = _folds(data.episode[fit], fit_eps, cfg.folds)
    xy = 1000.0 * np.linalg.norm(data.targets["cube-rel-hole"][:, :2], axis=1)  # (M,) mm from the hole axis
    near_test, near_fit = xy[test] < cfg.near_mm, xy[fit] < cfg.near_mm
    rows = []
    for view in data.views:
        x = data.features[view]
        x_fit, x_test = x[fit], x[test]
        cv = {t: np.zeros(len(cfg.alphas)) for t in TARGETS}
        for mask in folds:  # mask over the fitting frames: True = this fold's validation frames
            ridge = Ridge(x_fit[~mask], np.concatenate([data.targets[t][fit][~mask] for t in TARGETS], 1))
            pred = ridge.predict(x_fit[mask], cfg.alphas)  # (A, m, 3 * len(TARGETS))
            for j, t in enumerate(TARGETS):
                cv[t] += _euclid_mm(pred[..., 3 * j:3 * j + 3], data.targets[t][fit][mask]) * mask.sum()
        ridge = Ridge(x_fit, np.concatenate([data.targets[t][fit] for t in TARGETS], 1))
        for j, t in enumerate(TARGETS):
            best = int(np.argmin(cv[t]))
            alpha = cfg.alphas[best]
            y_fit, y_test = data.targets[t][fit], data.targets[t][test]
            pred = ridge.predict(x_test, [alpha])[0][:, 3 * j:3 * j + 3]  # (M_test, 3)
            base = np.broadcast_to(y_fit.mean(0), y_test.shape)  # (M_test, 3)
            row = dict(view=view, target=t, error_mm=float(_euclid_mm(pred, y_test)),
                       baseline_mm=float(_euclid_mm(base, y_test)), alpha=float(alpha), features=int(x.shape[1]),
                       near_frames=int(near_test.sum()))
            if near_test.any():
                base_near = y_fit[near_fit].mean(0) if near_fit.any() else y_fit.mean(0)  # (3,)
                row.update(near_error_mm=float(_euclid_mm(pred[near_test], y_test[near_test])),
                           near_baseline_mm=float(_euclid_mm(np.broadcast_to(base_near, y_test[near_test].shape),
                                                             y_test[near_test])))
            rows.append(row)
    return dict(rows=rows, episodes=dict(fit=int((~held).sum()), held_out=int(held.sum())),
                frames=dict(fit=int(fit.sum()), held_out=int(test.sum())),
                held_out_episodes=[n for n, h in zip(data.episodes, held) if h])


def probe_stores(stores: Sequence[str | Path], encoders: Sequence[Any], config: ProbeConfig | None = None,
                 progress: bool = False) -> list[dict[str, Any]]:
    """The probe report for each encoder on the same frames and the same split."""
    cfg = config or ProbeConfig()
    datas = load_probe_data(stores, encoders, cfg.batch_size, progress=progress)
    out = []
    for enc, data in zip(encoders, datas):
        rep = probe_arrays(data, cfg)
        rep.update(encoder=enc.config_dict(), tokens=[int(enc.num_patches), int(enc.dim)],
                   data=[str(s) for s in stores], val_fraction=cfg.val_fraction)
        out.append(rep)
    return out


def format_probe(report: dict[str, Any]) -> str:
    """A small table: targets down, views across, mm; the mean baseline last."""
    enc = {k: v for k, v in report["encoder"].items() if k != "path"}
    n, d = report["tokens"]
    head = (f"encoder {enc} ({n} tokens x {d} per view); fit {report['episodes']['fit']} episodes / "
            f"{report['frames']['fit']} frames, held out {report['episodes']['held_out']} / "
            f"{report['frames']['held_out']}; mean Euclidean error, mm")
    views = list(dict.fromkeys(r["view"] for r in report["rows"]))  # each camera, then all
    lines = [head, f"{'target':<19}" + "".join(f"{v:>8}" for v in views) + f"{'mean':>8}"]
    for t in TARGETS:
        rows = {r["view"]: r for r in report["rows"] if r["target"] == t}
        lines.append(f"{t:<19}" + "".join(f"{rows[v]['error_mm']:>8.1f}" for v in views)
                     + f"{rows[ALL]['baseline_mm']:>8.1f}")
    for t in TARGETS:
        rows = {r["view"]: r for r in report["rows"] if r["target"] == t}
        if "near_error_mm" in rows[ALL]:
            lines.append(f"{t + ' near':<19}" + "".join(f"{rows[v]['near_error_mm']:>8.1f}" for v in views)
                         + f"{rows[ALL]['near_baseline_mm']:>8.1f}   ({rows[ALL]['near_frames']} held-out frames "
                         f"with the cube near the hole)")
    return "\n".join(lines)
