"""One simulator-oracle-planned chunk, the old way (full ``TaskEnv.step`` per action, two restores,
unculled render) against the shipped fast rollout (``TaskEnv.simulate``), side by side in one run.

The real cost path: TinyWAM (``checkpoints/mini/tinywam``) gives the seed chunk and the target views, the
world model's patch-pixels encoder encodes them, CEM (32 candidates x 4 iterations, 16 actions) searches
with ``SimulatorDynamics`` inside a ``PlannedPolicy``. Old and new alternate, and must choose the same plan.
``--profile`` first prints per-call times of the pieces at 224 and 64 px. Wall time on a machine shared with
other jobs swings by 2x between runs; the CPU time of this process (lavapipe's threads included) does not.

    .venv/bin/python benchmarks/oracle.py                        # 2 repeats per way, camera 224 px
    LP_NUM_THREADS=1 .venv/bin/python benchmarks/oracle.py --profile --repeats 1
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np
import torch

from wamplan.envs.config import EnvConfig
from wamplan.envs.core import TaskEnv
from wamplan.planning import CEMConfig, make_cost, make_planner
from wamplan.planning.dynamics import SimulatorDynamics
from wamplan.planning.policy import PlannedPolicy
from wamplan.wam import load_wam
from wamplan.worldmodel.load import load_world_model


class FullStepDynamics(SimulatorDynamics):
    """The oracle before the fast rollout: every action through ``TaskEnv.step`` (ManiSkill's step with
    its observation and evaluation, then ours), restores in pairs, every body drawn."""

    @torch.inference_mode()
    def terminal(self, actions):
        views = []
        for cand in actions.detach().cpu().numpy():  # (L, A)
            self.restore()
            self.restore()
            for a in cand:
                self.env.step(a)
            frames = self.env.render(self.cameras, cull=False)
            views.append(np.stack([frames[c] for c in self.cameras]))  # (V, H, W, 3)
        self.restore()
        self.restore()
        imgs = torch.from_numpy(np.stack(views))  # (B, V, H, W, 3)
        z = self.encoder.encode(imgs.flatten(0, 1).to(self.encoder.device))  # (B·V, N, D)
        return z.reshape(*imgs.shape[:2], *z.shape[1:])  # (B, V, N, D)


def profile(sizes: tuple[int, ...], repeats: int) -> None:
    """ms per call (median and min over repeats), the pieces interleaved so that load from other processes hits
    all alike. Steps are timed as 16 in a row after a restore (one candidate's worth) and divided by 16."""
    envs = {s: TaskEnv(EnvConfig(camera_size=s)) for s in sizes}
    a = np.array([0.1, 0, 0, 0, 1], np.float32)
    calls = {}
    for s, env in envs.items():
        env.reset(2)
        for _ in range(10):
            env.step(np.array([0.2, 0, -0.2, 0, 1], np.float32))
        snap = env.snapshot()
        if s == sizes[0]:
            calls.update({
                "TaskEnv.step": (env, snap, 16, lambda e=env: e.step(a)),
                "base.step (ManiSkill: + observation, evaluation)": (
                    env, snap, 16, lambda e=env: e.base.step(torch.from_numpy(a[None]))),
                "_step_action (controller + physics)": (
                    env, snap, 16, lambda e=env: e.base._step_action(torch.from_numpy(a[None]))),
                "restore": (env, snap, 1, lambda e=env, sn=snap: e.restore(sn)),
                "restore, physics only (simulate)": (env, snap, 1, lambda e=env, sn=snap: e._restore_sim(sn)),
            })
        calls[f"render 3 cameras, {s} px"] = (env, snap, 1, lambda e=env: e.render(cull=False))
        calls[f"render 3 cameras, {s} px, culled"] = (env, snap, 1, lambda e=env: e.render(cull=True))
    times = {k: [] for k in calls}
    for _ in range(repeats):
        for k, (env, snap, n, fn) in calls.items():
            env.restore(snap)
            t0 = time.perf_counter()
            for _ in range(n):
                fn()
            times[k].append((time.perf_counter() - t0) / n)
    print("| per call | ms, median | ms, min |\n|---|---|---|")
    for k, v in times.items():
        print(f"| {k} | {1e3 * statistics.median(v):.1f} | {1e3 * min(v):.1f} |")
    for env in envs.values():
        env.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--wam", default="checkpoints/mini/tinywam")
    ap.add_argument("--wm", default="checkpoints/mini/wm_plain", help="its encoder encodes the views")
    ap.add_argument("--camera-size", type=int, default=224)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--warmup-chunks", type=int, default=2, help="open-loop WAM chunks before the planned one")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--profile", action="store_true", help="first print per-call times at 224 and 64 px")
    ap.add_argument("--profile-repeats", type=int, default=30)
    args = ap.parse_args()
    torch.set_num_threads(1)
    print(f"LP_NUM_THREADS={os.environ.get('LP_NUM_THREADS', 'default')}, torch threads 1, "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    if args.profile:
        profile((224, 64), args.profile_repeats)

    env = TaskEnv(EnvConfig(camera_size=args.camera_size))
    wam = load_wam(args.wam)
    _, enc = load_world_model(args.wm)
    planner = make_planner("cem", CEMConfig(num_candidates=32, num_elites=8, iterations=4))
    obs = env.reset(args.seed, with_images=True)
    for _ in range(args.warmup_chunks):  # reach a mid-episode boundary, the WAM open loop
        for a in wam.predict(obs, "").actions:
            env.step(a)
        obs = env.observe(with_images=True)
    snap = env.snapshot()
    ways = {"old (full step)": FullStepDynamics, "new (simulate)": SimulatorDynamics}
    times, cpu, plans = {k: [] for k in ways}, {k: [] for k in ways}, {k: [] for k in ways}
    for _ in range(args.repeats):
        for name, cls in ways.items():
            env.restore(snap)
            pol = PlannedPolicy(wam, planner, cls(env, enc), enc, make_cost("patch"))
            pol.reset(args.seed)
            t0, c0 = time.perf_counter(), time.process_time()
            pol.act(obs)  # a chunk boundary: plans the chunk
            times[name].append(time.perf_counter() - t0)
            cpu[name].append(time.process_time() - c0)  # all threads of this process, lavapipe's included
            plans[name].append(pol.last_plan.actions.numpy())  # (16, 5)
    for name, t in times.items():
        print(f"{name}: {statistics.median(t):.2f} s per chunk (runs {', '.join(f'{x:.2f}' for x in t)}), "
              f"CPU {statistics.median(cpu[name]):.2f} s")
    same = all(np.array_equal(a, b) for a, b in zip(*plans.values()))
    print(f"the same plan both ways: {same}")
    (old, new), (old_cpu, new_cpu) = ([statistics.median(t) for t in d.values()] for d in (times, cpu))
    print(f"CPU-time speed-up {old_cpu / new_cpu:.2f}x (the figure to trust on a shared machine)")
    print(f"speed-up {old / new:.2f}x")


if __name__ == "__main__":
    main()
