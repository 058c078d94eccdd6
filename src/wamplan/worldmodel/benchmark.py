"""The offline world-model benchmark: sibling statistics and latent errors per phase of the task.

A benchmark store holds counterfactual branch groups (``wamplan.data.branch``) at every chunk boundary of
held-out episodes (``scripts/wm_benchmark_store.py`` makes it). Each group is labelled with the phase of the
task at its boundary, read from the parent's record at that step (the last context frame):

* ``descent``: the stage flag ``aligned``, ``descended`` or ``seated`` is set (the cube is on the hole's axis
  above the mount, or already in the hole): the chunk decides the insertion;
* ``alignment``: ``lifted`` and over the mount (the cube's centre within ``data.alignment.NEAR`` = 30 mm of
  the hole's axis, its bottom above the mount's top less 2 mm, as ``wamplan data alignment`` counts it);
  the stage flags alone cannot tell this from carrying, hence the one geometric test;
* ``carry``: ``lifted`` anywhere else;
* ``grasp``: not ``lifted`` (approach, closing, lift-off; also a cube dropped back on the table).

The phases are cube-insertion's (:data:`PHASE_TASK`): they read its stage flags (the store's task's ``stages``)
and the cube's pose; a store of another task is one line (:func:`phase_task_of`).

Per phase (and over all groups) :func:`phase_table` pools with ``train.pool_siblings`` (the ``all`` row is
``train.evaluate_siblings``'s): ``sib_rel_hK`` (the share of the between-sibling variation of outcomes K frames
on that the model misses), ``sib_gain_hK`` (the slope of its predicted sibling differences on the true ones)
and the latent error of the siblings' windows, ``z_mse_h1`` / ``z_mse_hK`` (per-element MSE of the features,
as ``wm eval``'s ``z_mse``) with ``copy_z_mse_hK`` (copying the current frame) for scale.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

import h5py
import numpy as np
import torch
from torch.utils.data import Dataset

from wamplan.data.alignment import NEAR, hole_position
from wamplan.data.features import feature_key
from wamplan.data.readers import BranchGroups
from wamplan.data.store import EpisodeStore, stores_task
from wamplan.encoders.base import FrozenEncoder
from wamplan.envs.spec import TaskSpec
from wamplan.errors import UserError
from wamplan.worldmodel.load import load_world_model
from wamplan.worldmodel.predictor import WorldModelPredictor
from wamplan.worldmodel.siblings import pool_siblings, sibling_statistics
from wamplan.worldmodel.stores import encode_stores

PHASES = ("grasp", "carry", "alignment", "descent")
ALL = "all"
PHASE_TASK = "cube-insertion"  # the task whose stages and poses the phases are defined on


def phase_task_of(store: EpisodeStore) -> TaskSpec:
    """The task of ``store`` when the phases are defined for it; one line otherwise."""
    if store.task_name != PHASE_TASK:
        raise UserError(f"the benchmark's phases ({', '.join(PHASES)}) are defined for task {PHASE_TASK}, but "
                        f"{store.root} holds task '{store.task_name}'")
    return store.task


def phase_of(stages: np.ndarray, cube_pose: np.ndarray, hole: np.ndarray, cube_half: float,
             names: Sequence[str]) -> str:
    """The phase (module docstring) of one state: ``stages`` (S,) bool, the flags ``names`` (the task's
    ``stages``, in that order), ``cube_pose`` (7,) xyz + wxyz, ``hole`` (3,) the hole's top centre (x, y, mount
    height), ``cube_half`` metres."""
    flag = dict(zip(names, np.asarray(stages, bool).tolist()))
    if any(flag[s] for s in ("aligned", "descended", "seated")):
        return "descent"
    if not flag["lifted"]:
        return "grasp"
    xy = float(np.linalg.norm(cube_pose[:2] - hole[:2]))
    over = xy < NEAR and cube_pose[2] - cube_half > hole[2] - 0.002
    return "alignment" if over else "carry"


def group_phases(groups: BranchGroups) -> list[str]:
    """The phase of every group of ``groups`` at its boundary, read from its first sibling's record; one line
    for a store of a task the phases are not defined for."""
    # store -> (the hole's top centre (3,), the cube's half side, the task's stage names)
    places: dict[str, tuple[np.ndarray, float, tuple[str, ...]]] = {}
    out = []
    for members in groups.items:
        e = groups.episodes[members[0][0]]
        boundary, start = e.branch_at  # type: ignore[misc]  # the parent's boundary, and its step at the branch's 0
        root = str(Path(e.path).parent.parent)  # DIR/episodes/<file>.h5 -> DIR
        if root not in places:
            store = EpisodeStore(root)
            stages = phase_task_of(store).stages
            env = store.env
            places[root] = hole_position(env), float(env.get("cube_half_size", 0.02)), stages
        with h5py.File(e.path, "r") as f:
            out.append(phase_of(f["stages"][boundary - start], f["cube_pose"][boundary - start], *places[root]))
    return out


def store_fingerprint(root: str | Path) -> str:
    """A sha1 of a store's recorded trajectories (every episode's source, seed, actions, proprio, stage flags and
    poses, in file order), not of its files (they carry creation times): two collections that recorded the same
    episodes share it. Images are left out (hashing gigabytes); they are rendered from these states."""
    import hashlib

    h = hashlib.sha1()
    store = EpisodeStore(root)
    for path in store.episode_paths():
        with h5py.File(path, "r") as f:
            h.update(f"{f.attrs['source']}:{int(f.attrs['seed'])};".encode())
            for key in ("actions", "proprio", "stages", "cube_pose", "tcp_pose", "image_steps"):
                h.update(np.ascontiguousarray(f[key][:]).tobytes())
    return h.hexdigest()


def benchmark_parser(description: str) -> argparse.ArgumentParser:
    """A command line over checkpoints scored on branch-group stores: ``ckpt`` (one or more), ``--data`` (stores,
    comma separated, parsed to a list of paths) and ``--horizon``; the caller adds its own options."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("ckpt", nargs="+", help="predictor checkpoints or run directories")
    ap.add_argument("--data", required=True, type=lambda s: [Path(d) for d in s.split(",") if d],
                    help="episode stores with branch groups, comma separated")
    ap.add_argument("--horizon", type=int, default=4)
    return ap


def load_benchmark(ckpt: str | Path, data: Sequence[Path], horizon: int
                   ) -> tuple[WorldModelPredictor, FrozenEncoder, BranchGroups, list[str], tuple[str, ...]]:
    """A checkpoint's model (eval mode) and encoder, and every branch group of the stores ``data`` in that
    encoder's features (encoded first where missing), with the groups' phases and the stores' cameras; one line
    when the stores hold no branch groups."""
    model, enc = load_world_model(str(ckpt))
    _, cameras = stores_task(list(data))
    encode_stores(list(data), enc)
    groups = BranchGroups(list(data), model.cfg.frameskip, model.cfg.context, horizon, split="all",
                          features=feature_key(enc.config_dict()))
    if not len(groups):
        raise UserError(f"{', '.join(map(str, data))} holds no counterfactual branch groups: score a store "
                        f"collected with --branches (e.g. scripts/wm_benchmark_store.py)")
    return model.eval(), enc, groups, group_phases(groups), tuple(cameras)


def in_phase(labels: Sequence[str], phase: str) -> list[int]:
    """The indices of the groups labelled ``phase`` (every group for ``"all"``)."""
    return [i for i, p in enumerate(labels) if phase in (p, ALL)]


def phase_counts(root: str | Path, frameskip: int = 4, history: int = 3, horizon: int = 4) -> dict[str, int]:
    """Branch groups per phase in a store (of ``wm eval --horizon`` ``horizon`` with the mini predictor's window)."""
    groups = BranchGroups([root], frameskip=frameskip, history=history, horizon=horizon, split="all")
    labels = group_phases(groups)
    return {p: labels.count(p) for p in PHASES} | {ALL: len(labels), "siblings": groups.group}


def phase_table(model: WorldModelPredictor, groups: BranchGroups, horizon: int, batch_size: int = 8,
                phases: Sequence[str] | None = None, device: torch.device | None = None) -> dict[str, dict[str, float]]:
    """Phase (then ``"all"``) -> pooled statistics (module docstring) of ``groups``; phases without groups are
    left out. ``phases``: the groups' labels (default: :func:`group_phases`)."""
    labels = list(phases) if phases is not None else group_phases(groups)
    if len(labels) != len(groups):
        raise ValueError(f"{len(labels)} phase labels for {len(groups)} groups")
    return pool_by_phase(sibling_statistics(model, groups, horizon, batch_size, device), labels, horizon)


def pool_by_phase(s: dict[str, torch.Tensor], labels: Sequence[str], horizon: int) -> dict[str, dict[str, float]]:
    """Phase (then ``"all"``) -> ``train.pool_siblings`` of the groups with that label; ``s``: each statistic
    (G_total, K), one row per group, as ``train.sibling_statistics`` gives it (one view's ``[..., v]`` of its
    ``per="view"`` form pools that view alone)."""
    out = {}
    for phase in PHASES:
        idx = torch.tensor([i for i, p in enumerate(labels) if p == phase], dtype=torch.long)
        if len(idx):
            out[phase] = pool_siblings({k: v[idx] for k, v in s.items()}, horizon)
    out[ALL] = pool_siblings(s, horizon)
    return out


def format_phase_table(table: dict[str, dict[str, float]], horizon: int, plan_seconds: float | None = None,
                       title: str = "") -> str:
    """The table as text: one row per phase and ``all``; the planning time per chunk on the ``all`` row."""
    k = horizon
    cols = ("groups", f"sib_rel_h{k}", f"sib_gain_h{k}", "z_mse_h1", f"z_mse_h{k}", f"copy_z_mse_h{k}")
    head = f"{'phase':10s}" + "".join(f"{c:>14s}" for c in cols) + f"{'plan s/chunk':>14s}"
    lines = ([title] if title else []) + [head]
    for phase, row in table.items():
        cells = [f"{row['groups']:14d}"] + [f"{row[c]:14.4f}" for c in cols[1:]]
        plan = f"{plan_seconds:14.3f}" if phase == ALL and plan_seconds is not None else f"{'':14s}"
        lines.append(f"{phase:10s}" + "".join(cells) + plan)
    return "\n".join(lines)


def context_of(groups: Dataset, history: int, index: int = 0
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """A real planning context from group ``index``'s first sibling, for timing a search: z (H_ctx, V, N, D),
    q (H_ctx, P), a (H_ctx - 1, Δ·A) with H_ctx = ``history``, and its last frame (V, N, D) as a target."""
    item = groups[index]
    z, q, a = item["z"][0].float(), item["q"][0].float(), item["a"][0].float()  # (T, ...) of sibling 0
    return z[:history], q[:history], a[:history - 1], z[-1]
