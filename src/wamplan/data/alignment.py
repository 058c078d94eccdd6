"""``wamplan data alignment``: how close each episode of a store brought the cube to the hole, from the
privileged poses it records.

Per episode, over the steps where the cube is carried over the mount (its bottom at most 2 mm below the
mount's top, its centre within ``near`` of the hole's axis): the step of the smallest xy error to the
hole's axis, that error (and its x / y parts), the cube's yaw error to the hole there (mod 90°, as the task
scores it), the cube's offset from the TCP in xy (an off-centre grasp), and how many steps it spent there.
An episode that never gets there reports its smallest xy error over the whole episode.

The hole is the store's task's: its spec's ``hole_x`` and ``hole_y`` params and the store's ``mount_height``
(cube-insertion; a task without a hole, or a store without cube poses, is refused in one line).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from wamplan.data.store import LEGACY_TASK, EpisodeStore, StoreError
from wamplan.envs.spec import get_task
from wamplan.errors import UserError
from wamplan.policies.expert import quat_yaw, wrap_quarter  # the expert's yaw of a wxyz quaternion, mod 90°

NEAR = 0.03  # m: "over the mount" = cube centre within this of the hole's axis


@dataclass(frozen=True)
class EpisodeAlignment:
    source: str
    seed: int
    outcome: str
    over_steps: int  # steps carried over the mount
    step: int  # the step of the smallest xy error (over the mount if ever there)
    xy_mm: float  # cube centre to the hole's axis
    dx_mm: float
    dy_mm: float
    yaw_deg: float | None  # cube yaw to the hole's, mod 90°; None if never over the mount
    in_hand_mm: float | None  # cube centre to the TCP in xy at that step; None if never over the mount


def episode_alignment(cube_pose: np.ndarray, tcp_pose: np.ndarray, hole: np.ndarray, cube_half: float,
                      near: float = NEAR, **attrs: Any) -> EpisodeAlignment:
    """``cube_pose``, ``tcp_pose``: (T+1, 7) xyz + wxyz; ``hole``: (3,) the hole's top centre (x, y, mount height)."""
    cube_pose, tcp_pose, hole = (np.asarray(a, np.float64) for a in (cube_pose, tcp_pose, hole))
    d = cube_pose[:, :2] - hole[:2]  # (T+1, 2)
    err = np.linalg.norm(d, axis=1)  # (T+1,)
    over = (cube_pose[:, 2] - cube_half > hole[2] - 0.002) & (err < near)  # (T+1,)
    if not over.any():
        i = int(np.argmin(err))
        return EpisodeAlignment(over_steps=0, step=i, xy_mm=float(1e3 * err[i]), dx_mm=float(1e3 * d[i, 0]),
                                dy_mm=float(1e3 * d[i, 1]), yaw_deg=None, in_hand_mm=None, **attrs)
    i = int(np.flatnonzero(over)[np.argmin(err[over])])
    yaw = np.degrees(wrap_quarter(quat_yaw(cube_pose[i, 3:])))  # the hole is axis-aligned
    return EpisodeAlignment(over_steps=int(over.sum()), step=i, xy_mm=float(1e3 * err[i]), dx_mm=float(1e3 * d[i, 0]),
                            dy_mm=float(1e3 * d[i, 1]), yaw_deg=float(yaw),
                            in_hand_mm=1e3 * float(np.linalg.norm(cube_pose[i, :2] - tcp_pose[i, :2])), **attrs)


def hole_position(env: dict[str, Any]) -> np.ndarray:
    """The hole's top centre (x, y, mount height) of a store's env settings (``EpisodeStore.env``; the mount is
    fixed in the task: its spec's ``hole_x``, ``hole_y`` params), (3,) metres."""
    task = get_task(env.get("task", LEGACY_TASK))
    x, y = task.param("hole_x"), task.param("hole_y")
    if x is None or y is None:
        raise UserError(f"task '{task.name}' has no hole (its spec's params name no hole_x, hole_y): the cube's "
                        f"alignment to the hole is a cube-insertion diagnostic")
    return np.array([x, y, float(env.get("mount_height", 0.025))], np.float32)


def store_alignment(root: str | Path, near: float = NEAR) -> list[EpisodeAlignment]:
    """One :class:`EpisodeAlignment` per episode of the store ``root`` (sorted as the store lists them)."""
    store = EpisodeStore(root)
    hole, cube_half = hole_position(store.env), float(store.env.get("cube_half_size", 0.02))
    out = []
    for p in store.episode_paths():
        with store.open_episode(p) as f:
            if "cube_pose" not in f or "tcp_pose" not in f:
                raise StoreError(f"{p} records no cube or TCP pose; the alignment reads both")
            cube, tcp = f["cube_pose"][:], f["tcp_pose"][:]  # (T+1, 7) each
            source, seed, outcome = str(f.attrs["source"]), int(f.attrs["seed"]), str(f.attrs["outcome"])
        out.append(episode_alignment(cube, tcp, hole, cube_half, near, source=source, seed=seed, outcome=outcome))
    return out


def summary(rows: list[EpisodeAlignment]) -> dict[str, dict[str, Any]]:
    """Per outcome: episodes, and the median |xy|, |yaw| and in-hand offset of those that got over the mount."""
    out: dict[str, dict[str, Any]] = {}
    for outcome in sorted({r.outcome for r in rows}):
        rs = [r for r in rows if r.outcome == outcome]
        over = [r for r in rs if r.over_steps]
        out[outcome] = dict(episodes=len(rs), over_mount=len(over), median_xy_mm=_median([r.xy_mm for r in over]),
                            median_abs_yaw_deg=_median([abs(r.yaw_deg) for r in over]),
                            median_in_hand_mm=_median([r.in_hand_mm for r in over]))
    return out


def _median(xs: list[float]) -> float | None:
    return round(float(np.median(xs)), 1) if xs else None


def as_dicts(rows: list[EpisodeAlignment]) -> list[dict[str, Any]]:
    return [{k: (round(v, 2) if isinstance(v, float) else v) for k, v in asdict(r).items()} for r in rows]
