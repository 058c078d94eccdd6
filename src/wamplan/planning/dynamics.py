"""Dynamics backends: what turns a batch of candidate chunks into predicted terminal embeddings.

Both backends implement :class:`Dynamics`: ``prepare(context)`` once per chunk, then
``terminal(actions (B, L, A)) -> (B, V, N, D)`` for every batch of candidates. ``L`` is the number of
actions the backend's rollout covers (``covered``): Δ·⌊H/Δ⌋ for the learned world model (16 with Δ=4;
15 with the paper's Δ=5, the trailing action then being left to the WAM), H for the simulator.

* :class:`LearnedDynamics` rolls all candidates of an iteration out in one batched, KV-cached forward
  of the predictor; the context frames before the current one are encoded once per chunk (batch 1) and
  shared by every candidate and every CEM iteration.
* :class:`BlendedDynamics` (a diagnostic) moves a learned model's prediction a given share of the way to
  the simulator's, to measure how much of the model's error planning can bear.
* :class:`SimulatorDynamics` (the oracle) hands all candidates to ``TaskEnv.simulate`` (restore the
  chunk-boundary snapshot once, controller and physics only, render the terminal views with frustum
  culling), encodes the views, and restores the snapshot afterwards, so that the chosen plan executes
  from a restored state as each candidate did. One restore is exact: restoring twice gives bit-identical
  rollouts (PhysX's hidden state carries over from the previous rollout, and no restore clears it).

  A GPU-batched oracle plugs in at ``env.simulate(snapshot, actions (B, L, A)) -> views (B, V, H, W, 3)``:
  an env with ``num_envs = B`` on physx_cuda broadcasts the snapshot to its B sub-scenes, steps (B, A)
  actions L times and renders the B terminal frames with ManiSkill's camera groups; ``terminal``'s contract
  (B, L, A) -> (B, V, N, D) and this class stay as they are.

Every backend says which task it predicts (``task``, a :class:`~wamplan.envs.spec.TaskSpec`: the loaded world
model's, or the env's; None for a model that records none, e.g. one built in memory) and which views it stacks,
in order (``cameras``: the world model's, or the task's; None where it does not say). Backends combined into one
must share a task (one line otherwise).
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch

from wamplan.envs.spec import check_same_task
from wamplan.errors import UserError

if TYPE_CHECKING:
    from wamplan.envs.spec import TaskSpec


def task_name(obj: Any) -> str | None:
    """The name of the task ``obj`` (a WAM, a loaded world model, a backend) was made for, from its ``task`` (a
    TaskSpec or a name); None when it records none."""
    task = getattr(obj, "task", None)
    return getattr(task, "name", task)


def _shared_task(parts: list[Dynamics], what: str) -> TaskSpec | None:
    """The task of backends combined into one (the first that records one); one line naming ``what`` (``{i}``:
    the part's number, from 1) if another was made for a different task."""
    named = [(i, p) for i, p in enumerate(parts) if p.task is not None]
    for i, p in named[1:]:
        check_same_task(named[0][1].task.name, p.task.name, what.format(i=i + 1),
                        f"combine only parts made for '{named[0][1].task.name}'")
    return named[0][1].task if named else None


@dataclass
class PlanningContext:
    """The history a backend may use at a chunk boundary (the most recent frame last).

    z (Tc, V, N, D) encoded views of the history frames at stride Δ; q (Tc, P) their proprio;
    a (Tc-1, Δ·A) the action blocks executed from all but the current frame.
    """

    z: torch.Tensor
    q: torch.Tensor
    a: torch.Tensor


class Dynamics(abc.ABC):
    needs_history: bool = False
    task: TaskSpec | None = None  # the task it predicts; None: recorded nowhere
    cameras: tuple[str, ...] | None = None  # the views it stacks, in order; None: the task's

    @property
    @abc.abstractmethod
    def device(self) -> torch.device:
        """Where ``terminal`` returns its embeddings; the planner's candidates and the target live here too."""

    @abc.abstractmethod
    def covered(self, chunk: int) -> int:
        """How many leading actions of a ``chunk``-step chunk a rollout covers (the planner optimises these)."""

    def prepare(self, context: PlanningContext | None) -> None:
        """Per-chunk set-up (cache the context, take a snapshot)."""

    @abc.abstractmethod
    def terminal(self, actions: torch.Tensor) -> torch.Tensor:
        """actions (B, L, A) -> predicted terminal embeddings (B, V, N, D)."""

    def imagine(self, context: PlanningContext, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The frames a learned model predicts after ``context`` under the executed ``actions`` (L, A), L a
        multiple of its frameskip Δ -> z (L/Δ, V, N, D), q (L/Δ, P) float32: the frames Δ, 2Δ, ... steps after the
        context's last one (``history="imagined"``). Only a learned world model imagines."""
        raise UserError(f"{type(self).__name__} predicts no frames to stand in for unseen history; "
                        f"history='imagined' needs a learned world model")


class LearnedDynamics(Dynamics):
    """The block-causal world-model predictor (``wamplan.worldmodel``), rolled out in the predictor's own dtype
    (its parameters'); inputs are cast to it and the terminal latents come back as float32."""

    needs_history = True

    def __init__(self, predictor):
        self.model = predictor.eval()
        self.task = predictor.task  # a loaded checkpoint's task; None for a predictor built in memory without one
        self.cameras = predictor.cameras  # its views' cameras, in order (None: not known)
        self.frameskip = predictor.cfg.frameskip
        self.context = predictor.cfg.context
        self._prefix = None
        self._cur: tuple[torch.Tensor, torch.Tensor] | None = None

    @property
    def device(self) -> torch.device:
        return next(self.model.parameters()).device

    @property
    def dtype(self) -> torch.dtype:
        return next(self.model.parameters()).dtype

    def covered(self, chunk: int) -> int:
        return self.frameskip * (chunk // self.frameskip)

    @torch.inference_mode()
    def prepare(self, context: PlanningContext | None) -> None:
        if context is None:
            raise ValueError("the learned world model needs a history of frames to plan from")
        self._prefix, self._cur = self._start(context)

    def _start(self, context: PlanningContext):
        """``context`` in the predictor's device and dtype -> (its cached prefix, batch 1, shared by every rollout
        from it; the current frame: z (1, V, N, D), q (1, P)). The context may be one frame."""
        dev, dt = self.device, self.dtype
        z, q, a = (x.to(dev, dt) for x in (context.z, context.q, context.a))  # (Tc, V, N, D), (Tc, P), (Tc-1, ΔA)
        return self.model.encode_prefix(z[None, :-1], q[None, :-1], a[None]), (z[None, -1], q[None, -1])

    def _blocks(self, actions: torch.Tensor) -> torch.Tensor:
        """actions (B, L, A) -> the rollout's action blocks (B, S, Δ·A) in the predictor's device and dtype."""
        b, length, na = actions.shape
        return actions.to(self.device, self.dtype).reshape(b, length // self.frameskip, self.frameskip * na)

    @torch.inference_mode()
    def imagine(self, context: PlanningContext, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        prefix, cur = self._start(context)  # its own, not the planning point's (prepare's)
        zs, qs = self.model.rollout_from_prefix(prefix, *cur, self._blocks(actions[None]))  # (1, S, V, N, D), (1, S, P)
        return zs[0].float(), qs[0].float()  # (S, V, N, D), (S, P)

    @torch.inference_mode()
    def terminal(self, actions: torch.Tensor) -> torch.Tensor:
        z, _ = self.model.rollout_from_prefix(self._prefix, *self._cur, self._blocks(actions))  # (B, S, V, N, D)
        return z[:, -1].float()  # (B, V, N, D)


class SimulatorDynamics(Dynamics):
    """The simulator oracle: privileged, exact dynamics, at the price of stepping and rendering. It renders
    ``cameras`` (default: the env's task's), in that order."""

    def __init__(self, env, encoder, cameras: tuple[str, ...] | None = None):
        self.env, self.encoder, self.task = env, encoder, env.task
        self.cameras = tuple(cameras) if cameras else env.task.cameras
        self._snap = None

    @property
    def device(self) -> torch.device:
        return self.encoder.device

    def covered(self, chunk: int) -> int:
        return chunk

    def prepare(self, context: PlanningContext | None) -> None:
        self._snap = self.env.snapshot()

    def restore(self) -> None:
        self.env.restore(self._snap)

    @torch.inference_mode()
    def terminal(self, actions: torch.Tensor) -> torch.Tensor:
        try:
            views = self.env.simulate(self._snap, actions.detach().cpu().numpy(), self.cameras)  # (B, V, H, W, 3)
        finally:
            self.restore()  # the chosen plan executes from a restored state, as every candidate ran
        imgs = torch.from_numpy(views)  # (B, V, H, W, 3) uint8
        b, nv = imgs.shape[:2]
        z = self.encoder.encode(imgs.flatten(0, 1).to(self.encoder.device))  # (B·V, N, D)
        return z.reshape(b, nv, *z.shape[1:])  # (B, V, N, D)


class BlendedDynamics(Dynamics):
    """A diagnostic, not a method: a learned model's prediction moved a share ``weight`` of the way to the
    simulator's exact outcome, ``z = (1 - w) z_model + w z_sim``, with the same encoder.

    Weight 0 plans as the learned model does, 1 as the oracle does; in between the model's error on every
    candidate is scaled by 1 - w, keeping its structure (which candidates it confuses, and how). Planning
    success against w says how much of the model's error must go before planning reaches the oracle, which
    is what a better world model must buy. It costs what the oracle costs (every candidate is simulated).
    """

    def __init__(self, model: Dynamics, oracle: SimulatorDynamics, weight: float):
        if not 0.0 <= weight <= 1.0:
            raise ValueError(f"blend weight {weight} is outside [0, 1]; 0 is the learned model, 1 the simulator")
        self.model, self.oracle, self.weight = model, oracle, float(weight)
        self.task = _shared_task([oracle, model], "checkpoint of the world model in the blend")
        self.cameras = model.cameras or oracle.cameras
        self.needs_history = model.needs_history
        self.frameskip = getattr(model, "frameskip", None)
        self.context = getattr(model, "context", 1)

    @property
    def device(self) -> torch.device:
        return self.model.device

    def covered(self, chunk: int) -> int:
        return min(self.model.covered(chunk), self.oracle.covered(chunk))

    def prepare(self, context: PlanningContext | None) -> None:
        self.model.prepare(context)
        self.oracle.prepare(context)

    def imagine(self, context: PlanningContext, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.model.imagine(context, actions)  # the history is the learned model's

    def terminal(self, actions: torch.Tensor) -> torch.Tensor:
        z_model = self.model.terminal(actions).float()  # (B, V, N, D)
        z_sim = self.oracle.terminal(actions).float().to(z_model.device)  # (B, V, N, D)
        return torch.lerp(z_model, z_sim, self.weight)  # (B, V, N, D)
