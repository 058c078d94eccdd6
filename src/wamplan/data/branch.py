"""Counterfactual branches: at each chunk boundary of an on-policy episode, the same state under perturbed chunks.

A world model that plans must tell apart the outcomes of *nearby* chunks from the *same* state: that is
what CEM asks of it. Ordinary on-policy episodes show one chunk per state; branches show several.

``collect_branched`` runs the policy's episode as ``collect_one`` does and snapshots the simulator at
every chunk boundary t (t = H, 2H, ... with at least ``context_steps`` of history; only those within
``steps`` when it is set, e.g. the descent onto the mount, where the planner's choices decide the outcome).
After the episode it restores each snapshot and executes ``branches`` chunks drawn as CEM draws its
candidates: the chunk the policy executed from t plus Gaussian noise (one ``sigma`` per branch, cycling
through ``sigmas``), clipped to the action bounds. Each branch is stored as its own short episode in the ordinary schema,
re-based to start ``context_steps`` before t: the parent's history (its states, actions and frames)
followed by the branch's H steps, so the world model's windows (history frames, then predicted frames)
start in the shared past and end in the branch's own future.

Seeds: branch ``j`` of parent seed ``s`` is stored with seed ``s * 1000 + j``; the parent is written
last, so a parent in the store means its branches are complete (``drop_unfinished_branches`` removes the
branches of a parent that was interrupted).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from wamplan.config import check_numbers
from wamplan.data.record import STATE_KEYS, collect_one, record_state, stack_state
from wamplan.data.store import BRANCH_SEED_FACTOR, EpisodeData, EpisodeStore, parent_episode
from wamplan.envs.core import TaskEnv
from wamplan.policies.base import Policy
from wamplan.provenance import provenance



@dataclass(frozen=True)
class BranchSpec:
    branches: int = 8  # perturbed chunks per boundary
    chunk: int = 16  # H: the boundaries' spacing when the policy has no chunk_length of its own
    context_steps: int = 8  # history kept before t: (H_ctx - 1) * Δ of the world model
    sigmas: tuple[float, ...] = (0.05, 0.1, 0.2)  # noise std per branch, cycled
    rng_seed: int = 0
    steps: tuple[int, int] | None = None  # (lo, hi): branch only the boundaries t with lo <= t <= hi

    def __post_init__(self):
        check_numbers(self)
        if self.branches <= 0 or self.chunk <= 0 or self.context_steps < 0 or not self.sigmas:
            raise ValueError(f"invalid branch spec {self}")
        if self.steps is not None and not (len(self.steps) == 2 and 0 <= self.steps[0] <= self.steps[1]):
            raise ValueError(f"branch steps {self.steps} must be two steps lo <= hi")

    def branches_at(self, t: int) -> bool:
        return self.steps is None or self.steps[0] <= t <= self.steps[1]


def branch_source(parent_source: str) -> str:
    """``policy:tinywam`` -> ``branch:tinywam``."""
    return "branch:" + parent_source.split(":", 1)[-1]


def parent_seed(branch_seed: int) -> int:
    return parent_episode("branch:", branch_seed)[1]


def collect_branched(env: TaskEnv, policy: Policy, seed: int, source: str, image_every: int,
                     spec: BranchSpec, max_steps: int | None = None) -> tuple[EpisodeData, list[EpisodeData]]:
    """The parent episode (as ``collect_one``) and its branches (see the module docstring)."""
    chunk = getattr(policy, "chunk_length", None) or spec.chunk  # a WAM's own chunk length sets the boundaries
    spec = replace(spec, chunk=chunk)
    snaps: dict[int, object] = {}
    limit = min(max_steps or env.max_episode_steps, env.max_episode_steps)
    if spec.branches * (limit // spec.chunk) >= BRANCH_SEED_FACTOR:
        raise ValueError(f"{spec.branches} branches x {limit // spec.chunk} boundaries would number {BRANCH_SEED_FACTOR} "
                         f"or more branches per episode, past the seed space s * {BRANCH_SEED_FACTOR} + j; use fewer "
                         f"--branches")
    if spec.chunk % image_every or spec.context_steps % image_every:
        raise ValueError(f"image_every {image_every} must divide the chunk {spec.chunk} and the context "
                         f"{spec.context_steps}")

    def at_boundary(e: TaskEnv, obs, action) -> None:
        t = obs.step
        if (t % spec.chunk == 0 and t >= max(spec.context_steps, 1) and t + spec.chunk <= limit
                and spec.branches_at(t)):
            snaps[t] = e.snapshot()

    parent = collect_one(env, policy, seed, source, image_every, max_steps, on_step=at_boundary)
    rng = np.random.default_rng([spec.rng_seed, seed])
    out, j = [], 0
    for t, snap in sorted(snaps.items()):
        if t >= parent.length:  # the episode ended (success) at this boundary: nothing was executed from it
            continue
        base = parent.actions[t:t + spec.chunk]  # (<=H, A) the policy's chunk as executed
        if len(base) < spec.chunk:  # the episode succeeded mid-chunk: hold its last action
            base = np.concatenate([base, np.repeat(base[-1:], spec.chunk - len(base), 0)])
        for b in range(spec.branches):
            sigma = spec.sigmas[b % len(spec.sigmas)]
            acts = np.clip(base + rng.normal(0.0, sigma, base.shape), -1.0, 1.0).astype(np.float32)  # (H, A)
            out.append(_branch_episode(env, snap, parent, t, acts, seed * BRANCH_SEED_FACTOR + j,
                                       branch_source(source), image_every, spec, sigma))
            j += 1
    return parent, out


def _branch_episode(env: TaskEnv, snap, parent: EpisodeData, t: int, actions: np.ndarray, seed: int,
                    source: str, image_every: int, spec: BranchSpec, sigma: float) -> EpisodeData:
    s0 = t - spec.context_steps  # the branch episode's step 0 is the parent's step s0
    cameras = env.task.cameras
    rec = {k: [None if getattr(parent, k) is None else getattr(parent, k)[i] for i in range(s0, t + 1)]
           for k in STATE_KEYS}
    keep = [k for k, st in enumerate(parent.image_steps) if s0 <= st <= t]  # the parent's frames in the history
    image_steps = [int(parent.image_steps[k]) - s0 for k in keep]
    frames = {c: [parent.images[c][k] for k in keep] for c in cameras}
    env.restore(snap)
    for i, a in enumerate(actions, start=1):
        want = (spec.context_steps + i) % image_every == 0
        obs, _ = env.step(a, with_images=want)
        record_state(rec, env, obs)
        if want:
            image_steps.append(spec.context_steps + i)
            for c in cameras:
                frames[c].append(obs.images[c])
    arrays = stack_state(rec)
    return EpisodeData(seed=seed, source=source, success=env.success, outcome=env.outcome(),
                       actions=np.concatenate([parent.actions[s0:t], actions]).astype(np.float32),
                       proprio=arrays["proprio"], stages=arrays["stages"], cube_pose=arrays["cube_pose"],
                       tcp_pose=arrays["tcp_pose"], target_pose=arrays["target_pose"], sim_state=arrays["sim_state"],
                       drive_targets=arrays["drive_targets"], image_steps=np.asarray(image_steps, np.int32),
                       images={c: np.stack(frames[c]) for c in cameras}, reached=dict(env.reached),
                       policy=dict(parent.policy, branch_of=int(parent.seed), branch_step=int(t), sigma=float(sigma)),
                       provenance=provenance(parent_seed=int(parent.seed), start_step=int(s0)))


def drop_unfinished_branches(store: EpisodeStore, parent_source: str) -> int:
    """Delete the branch episodes whose parent episode is not in the store (an interrupted parent); returns
    how many. Re-collecting that parent writes its branches again."""
    done = store.finished_seeds(parent_source)
    src = branch_source(parent_source)
    n = 0
    for s in store.finished_seeds(src):
        if parent_seed(s) not in done:
            store.episode_path(src, s).unlink(missing_ok=True)
            n += 1
    return n
