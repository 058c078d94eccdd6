"""Where the cube went during an evaluation episode (privileged, for reading failures, never for acting).

``CubeTrace`` is a ``run_episode`` hook: every ``every`` steps it notes the cube's distance from the hole's
axis, its height, tilt and yaw, whether the fingers grasp it, and the gripper's opening. ``release``
reads the moment that decides the insertion off a trace: the first sample after a grasp where the cube is
no longer grasped, i.e. where and how high it was let go (inside the hole: its bottom below the mount's top).

    trace = CubeTrace(every=4)
    run_episode(env, policy, seed, on_obs=trace)
    trace.rows   # [{"t": 0, "xy_mm": 121.3, "bottom_mm": 0.0, "tilt": 0.0, "yaw": 0.31, "grasped": False, "grip_mm": 80.0}, ...]
    release(trace.rows)   # {"t": 148, "xy_mm": 6.2, "bottom_mm": 43.9, ...} or None (never released after a grasp)
"""

from __future__ import annotations

from typing import Any


class CubeTrace:
    """``on_obs`` hook: one row of the cube's state every ``every`` steps (and at the episode's last step,
    which the caller adds with :meth:`close`)."""

    def __init__(self, every: int = 4):
        if every < 1:
            raise ValueError(f"every must be >= 1 step, got {every}")
        self.every, self.rows = every, []
        self._last: dict[str, Any] | None = None

    def __call__(self, env, obs, action) -> None:
        m = env.metrics
        row = dict(t=obs.step, xy_mm=round(1000 * m.get("cube_xy_error", float("nan")), 2),
                   bottom_mm=round(1000 * m.get("cube_bottom", float("nan")), 2),
                   tilt=round(m.get("cube_tilt", float("nan")), 4), yaw=round(m.get("cube_yaw_error", float("nan")), 4),
                   grasped=bool(m.get("grasped", False)), grip_mm=round(1000 * float(obs.proprio[0]), 2))
        self._last = row
        if obs.step % self.every == 0:
            self.rows.append(row)

    def close(self) -> list[dict[str, Any]]:
        """The rows, with the episode's last step added when it fell between two samples."""
        if self._last is not None and (not self.rows or self.rows[-1]["t"] != self._last["t"]):
            self.rows.append(self._last)
        return self.rows


def release(rows: list[dict[str, Any]]) -> dict[str, Any] | None:
    """The first row after a grasp where the cube is no longer grasped (the release), or None."""
    held = False
    for row in rows:
        if row["grasped"]:
            held = True
        elif held:
            return dict(row)
    return None
