"""Where the cube went during an evaluation episode (privileged, for reading failures, never for acting).

``CubeTrace`` is a ``run_episode`` hook. Every ``every`` steps it keeps a row of the cube's distance from the
hole's axis, its height, tilt and yaw, whether the fingers grasp it, and the gripper's opening; at every step
it watches for the moment that decides the insertion: the last step at which the cube, once lifted in the
fingers, stopped being grasped, i.e. where and how high it was finally let go (inside the hole: its bottom
below the mount's top). Grasps that never lifted the cube (a graze at the start) do not count.

    trace = CubeTrace(every=4)
    run_episode(env, policy, seed, on_obs=trace)
    trace.close()   # [{"t": 0, "xy_mm": 121.3, "bottom_mm": 0.0, "tilt": 0.0, "yaw": 0.31, "grasped": False, "grip_mm": 80.0}, ...]
    trace.release   # {"t": 148, "xy_mm": 6.2, "bottom_mm": 43.9, ..., "held_mm": [5.8, 45.0]} or None
    trace.held_at_end  # grasped at the last step (e.g. seated while still holding: nothing let go)

It reads the cube task's measures (:data:`METRICS` and the stages :data:`STAGES` of every step's metrics, the
gripper's opening as the first proprio entry); :meth:`CubeTrace.fits` says whether a task reports them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from wamplan.envs.spec import TaskSpec

METRICS = ("cube_xy_error", "cube_bottom", "cube_tilt", "cube_yaw_error")  # the continuous measures read
STAGES = ("grasped", "lifted")  # the stage flags read


class CubeTrace:
    """``on_obs`` hook: rows every ``every`` steps (:meth:`close` adds the last step), the final release at
    full resolution (``release``), and how many times a lifted grasp was lost (``releases``)."""

    def __init__(self, every: int = 4):
        if every < 1:
            raise ValueError(f"every must be >= 1 step, got {every}")
        self.every, self.rows = every, []
        self.releases = 0
        self._last: dict[str, Any] | None = None
        self._let_go: dict[str, Any] | None = None
        self._lifted = False

    @staticmethod
    def fits(task: TaskSpec) -> bool:
        """Whether ``task`` reports what the trace reads (the cube task's :data:`METRICS` and :data:`STAGES`)."""
        return set(METRICS) <= set(task.metrics) and set(STAGES) <= set(task.stages)

    @property
    def held_at_end(self) -> bool:
        return bool(self._last and self._last["grasped"])

    @property
    def release(self) -> dict[str, Any] | None:
        """The final let-go: the last step after the cube was first lifted in the fingers at which it was no
        longer grasped, with where it was on the step before (``held_mm`` = [xy, bottom]); None while it is
        still held, or if it was never lifted."""
        return None if self.held_at_end else self._let_go

    def __call__(self, env, obs, action) -> None:
        m = env.metrics
        row = dict(t=obs.step, xy_mm=round(1000 * m.get("cube_xy_error", float("nan")), 2),
                   bottom_mm=round(1000 * m.get("cube_bottom", float("nan")), 2),
                   tilt=round(m.get("cube_tilt", float("nan")), 4), yaw=round(m.get("cube_yaw_error", float("nan")), 4),
                   grasped=bool(m.get("grasped", False)), grip_mm=round(1000 * float(obs.proprio[0]), 2))
        prev, self._last = self._last, row
        self._lifted |= row["grasped"] and bool(m.get("lifted", False))  # the task's own "lifted" flag
        if self._lifted and prev is not None and prev["grasped"] and not row["grasped"]:
            self.releases += 1
            self._let_go = dict(row, held_mm=[prev["xy_mm"], prev["bottom_mm"]])
        if obs.step % self.every == 0:
            self.rows.append(row)

    def close(self) -> list[dict[str, Any]]:
        """The rows, with the episode's last step added when it fell between two samples."""
        if self._last is not None and (not self.rows or self.rows[-1]["t"] != self._last["t"]):
            self.rows.append(self._last)
        return self.rows

    def summary(self) -> dict[str, Any]:
        """What a record keeps: the rows, the final release, the number of releases, held at the end."""
        return dict(trace=self.close(), release=self.release, releases=self.releases, held_at_end=self.held_at_end)
