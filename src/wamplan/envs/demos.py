"""ManiSkill's motion-planning demonstrations, written in ManiSkill's own trajectory format (``.h5`` + ``.json``).

:func:`motion_planning_demos` runs ManiSkill's scripted solution of a task (``mani_skill.examples.motionplanning``,
``pd_joint_pos``) on a range of seeds through ManiSkill's ``RecordEpisode`` wrapper, as ManiSkill's own
``python -m mani_skill.examples.motionplanning.panda.run`` does, and keeps the solved episodes. The file it writes
is what ``wamplan data import --format maniskill`` reads (after ManiSkill's ``replay_trajectory`` has converted it
to the task's controller, which the importer does itself).

ManiSkill 3.0.1 pins mplib 0.1.1, whose planner crashes on construction on this machine; mplib 0.2 works once the
three planner methods ManiSkill's solutions call are adapted to its new signatures (:class:`_CompatPlanner`),
which this module does while a solution runs.
"""

from __future__ import annotations

import contextlib
import json
import sys
import time
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from wamplan.errors import UserError


def _compat_planner_class():
    """A subclass of mplib 0.2's ``Planner`` that accepts mplib 0.1's calls (as ManiSkill 3.0.1 makes them)."""
    import mplib

    if not hasattr(mplib, "Pose"):  # mplib 0.1: ManiSkill's calls fit as they are
        return mplib.Planner

    def pose(p7) -> "mplib.Pose":
        p7 = np.asarray(p7, np.float64)  # (7,) xyz + wxyz
        return mplib.Pose(p7[:3], p7[3:])

    class _CompatPlanner(mplib.Planner):
        def set_base_pose(self, p7):
            super().set_base_pose(p7 if isinstance(p7, mplib.Pose) else pose(p7))

        def plan_screw(self, target_pose, qpos, time_step=0.1, use_point_cloud=False, use_attach=False, **kw):
            return super().plan_screw(pose(target_pose), qpos, time_step=time_step, **kw)

        def plan_qpos_to_pose(self, goal_pose, current_qpos, time_step=0.1, rrt_range=0.1, planning_time=1,
                              wrt_world=True, use_point_cloud=False, use_attach=False, planner_name=None, **kw):
            return self.plan_pose(pose(goal_pose), current_qpos, time_step=time_step, rrt_range=rrt_range,
                                  planning_time=planning_time, wrt_world=wrt_world, **kw)

    return _CompatPlanner


@contextlib.contextmanager
def _compatible_mplib() -> Iterator[None]:
    """While inside, ManiSkill's motion-planning modules build :func:`_compat_planner_class` planners."""
    try:
        import mplib
    except ImportError as e:
        raise UserError("ManiSkill's motion planner needs mplib; install it with `pip install --no-deps mplib==0.2.1 "
                        "toppra transforms3d` (scripts/setup.sh does)") from e
    from mani_skill.examples.motionplanning.base_motionplanner import motionplanner as base

    original = base.mplib.Planner
    base.mplib.Planner = _compat_planner_class()
    try:
        yield
    finally:
        base.mplib.Planner = original
        del mplib


def solution_for(env_id: str) -> Callable:
    """ManiSkill's scripted motion-planning solution of ``env_id`` (Panda tasks)."""
    from mani_skill.examples.motionplanning.panda.run import MP_SOLUTIONS

    if env_id not in MP_SOLUTIONS:
        raise UserError(f"ManiSkill has no motion-planning solution for {env_id}; it has one for "
                        f"{', '.join(sorted(MP_SOLUTIONS))}")
    return MP_SOLUTIONS[env_id]


def motion_planning_demos(env_id: str, out: str | Path, seeds: range, *, log=None) -> dict:
    """Run ManiSkill's motion-planning solution of ``env_id`` on ``seeds``; keep the solved episodes in
    ``out`` (``out.h5`` + ``out.json``, ManiSkill's trajectory format, ``pd_joint_pos``, env states recorded).
    Returns counts and timing. Episodes whose plan fails or ends unsolved are not written."""
    import gymnasium as gym
    from mani_skill.utils.wrappers.record import RecordEpisode

    import wamplan.envs  # noqa: F401  (configures Vulkan before SAPIEN loads)

    log = log or (lambda *a, **k: print(*a, **k, file=sys.stderr))  # stdout is silenced: the solutions print
    out = Path(out).with_suffix("")
    if out.with_suffix(".h5").exists():
        raise UserError(f"{out.with_suffix('.h5')} exists; pass a new path (demonstrations are never overwritten)")
    out.parent.mkdir(parents=True, exist_ok=True)
    solve = solution_for(env_id)
    env = gym.make(env_id, obs_mode="none", control_mode="pd_joint_pos", render_mode="rgb_array",
                   sim_backend="physx_cpu")
    env = RecordEpisode(env, output_dir=str(out.parent), trajectory_name=out.name, save_video=False,
                        source_type="motionplanning", record_reward=False, save_on_reset=False,
                        source_desc="ManiSkill's motion-planning solution, run by wamplan data demos")
    solved, lengths, t0 = [], [], time.perf_counter()
    with _compatible_mplib(), contextlib.redirect_stdout(None):
        for i, seed in enumerate(seeds):
            try:
                res = solve(env, seed=seed, debug=False, vis=False)
            except Exception:  # a failed plan inside ManiSkill's solution: the seed is unsolved
                res = -1
            ok = res != -1 and bool(res[-1]["success"].item())
            env.flush_trajectory(save=ok)
            if ok:
                solved.append(seed)
                lengths.append(int(res[-1]["elapsed_steps"].item()))
            if (i + 1) % 10 == 0 or i + 1 == len(seeds):
                log(f"[demos] {i + 1}/{len(seeds)} seeds, {len(solved)} solved, "
                    f"{(time.perf_counter() - t0) / (i + 1):.2f} s a seed", flush=True)
    env.close()
    summary = dict(env_id=env_id, seeds=[seeds.start, seeds.stop], solved=len(solved), tried=len(seeds),
                   mean_length=float(np.mean(lengths)) if lengths else None,
                   seconds=round(time.perf_counter() - t0, 1), h5=str(out.with_suffix(".h5")))
    Path(str(out) + ".summary.json").write_text(json.dumps(summary, indent=1))
    return summary


def main(argv: list[str] | None = None) -> int:
    """``python -m wamplan.envs.demos --task NAME --seeds A-B --out PATH`` (what scripts/maniskill_demos.sh runs)."""
    import argparse

    from wamplan.envs.spec import get_task

    p = argparse.ArgumentParser(prog="python -m wamplan.envs.demos", description=motion_planning_demos.__doc__)
    p.add_argument("--task", default="peg-insertion-side", help="a registered task with a ManiSkill motion-planning "
                                                                "solution (default: peg-insertion-side)")
    p.add_argument("--seeds", required=True, help="seed range A-B (inclusive), e.g. 10000-10999")
    p.add_argument("--out", required=True, help="the trajectory to write: OUT.h5 and OUT.json")
    args = p.parse_args(argv)
    try:
        lo, _, hi = args.seeds.partition("-")
        seeds = range(int(lo), int(hi or lo) + 1)
        print(json.dumps(motion_planning_demos(get_task(args.task).env_id, args.out, seeds)))
    except (UserError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
