"""The history a learned world model conditions on: which frames of an episode to keep, and the context
(frames and the actions executed between them) it gets at a planning point.

At planning point t (a chunk boundary, or every ``period`` steps for a robot that runs part of each chunk) the
history is the frames at
t-(Tc-1)Δ, ..., t-Δ, t with the actions executed between them, anchored to t whether or not Δ divides the
chunk (Δ=5, H=16: frames t-10, t-5, t). Before step 0 the robot rested: with ``rest_state`` the first frame
stands in for the earlier ones, with the task's ``hold_action`` (arm still, gripper open) between them; without it, a
history reaching before step 0 is no history (None). A frame that should exist but was never shown is a
:class:`PlanningError`, never a silently unplanned chunk.

With ``imagine`` (``history="imagined"``) only the planning points' own frames are seen: the history frames
between them are the world model's predictions, rolled from the context of the latest frame seen on their grid
(itself partly imagined; at step 0 the first frame alone, or the rest-state history) under the actions executed
since.
So a client that posts only at chunk boundaries gets a Δ < H model's history.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from wamplan.envs.spec import Observation
from wamplan.planning.dynamics import Dynamics, PlanningContext
from wamplan.planning.policy_config import PlanningError

Encode = Callable[[dict[str, np.ndarray]], torch.Tensor]  # camera -> (H, W, 3) uint8 views -> (V, N, D)
Imagine = Callable[[PlanningContext, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]  # Dynamics.imagine


class FrameHistory:
    """The frames and executed actions of one episode, kept for a dynamics backend's planning contexts.

    ``frameskip`` Δ and ``context`` Tc are the dynamics' (a learned world model's stride and number of frames);
    ``chunk`` H is the WAM's; ``period`` (default H) is how many steps apart the planning points are (a robot that
    runs K < H steps of each chunk before asking again: K). ``keeps_frames`` is False for a backend that needs no history (the simulator):
    then only the executed actions are kept. Frames are encoded with ``encode`` and kept on ``device``.
    ``hold_action`` (A,): the action of the rest before step 0 (the task's ``hold_action``), needed with
    ``rest_state``. ``imagine`` (the dynamics' :meth:`~wamplan.planning.dynamics.Dynamics.imagine`): predict the
    frames between planning points instead of seeing them (:func:`~wamplan.planning.policy_config.check_fits` says
    which settings allow it).
    """

    def __init__(self, chunk: int, frameskip: int, context: int, encode: Encode, device: torch.device, *,
                 keeps_frames: bool = True, rest_state: bool = False, hold_action: np.ndarray | None = None,
                 period: int | None = None, imagine: Imagine | None = None):
        if rest_state and hold_action is None:
            raise ValueError("a rest-state history needs the task's hold_action (the action of the rest)")
        self.chunk, self.frameskip, self.context = chunk, frameskip, context
        self.period = period or chunk
        self.encode, self.device = encode, device
        self.keeps_frames, self.rest_state, self.hold_action = keeps_frames, rest_state, hold_action
        self.imagine = imagine if keeps_frames else None
        self.reset()

    @classmethod
    def for_dynamics(cls, dynamics: Dynamics, chunk: int, encode: Encode, hold_action: np.ndarray,
                     rest_state: bool = False, period: int | None = None, imagined: bool = False) -> FrameHistory:
        """The history ``dynamics`` needs (its frameskip and context; none for a backend without history);
        ``hold_action`` (A,): the task's rest action; ``period``: steps between planning points (default the
        chunk); ``imagined``: the frames between planning points predicted by ``dynamics``, not seen."""
        return cls(chunk, getattr(dynamics, "frameskip", chunk), getattr(dynamics, "context", 1), encode,
                   dynamics.device, keeps_frames=dynamics.needs_history, rest_state=rest_state,
                   hold_action=hold_action, period=period, imagine=dynamics.imagine if imagined else None)

    def reset(self) -> None:
        """Start a new episode."""
        self.frames: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}  # step -> (z (V, N, D), q (P,)) on device
        self.seen: set[int] = set()  # the steps of the frames shown, not imagined
        self.executed: list[np.ndarray] = []  # (A,) per step, clipped to [-1, 1]: the action run at that step

    def steps(self, t: int) -> list[int]:
        """The steps of the history frames for the planning point t, oldest first."""
        return [t - i * self.frameskip for i in range(self.context - 1, -1, -1)]

    def real(self, t: int) -> bool:
        """Whether the history of planning point t lies inside the episode (none of it synthesised)."""
        return self.steps(t)[0] >= 0

    def wants(self, step: int) -> bool:
        """Whether ``step`` is a history frame: t - iΔ (0 <= i < Tc) for some planning point t >= step, the
        planning points being every ``period`` steps (the chunk boundaries by default). An imagined history sees
        only the planning points."""
        if self.imagine is not None:
            return self.keeps_frames and step % self.period == 0
        return self.keeps_frames and any((step + i * self.frameskip) % self.period == 0 for i in range(self.context))

    def observe(self, obs: Observation) -> None:
        """Encode and keep the frame of ``obs`` if it is a history frame (see :meth:`wants`) not kept yet, and
        forget the frames no planning point needs any more."""
        t = obs.step
        if not self.wants(t) or t in self.frames:
            return
        if obs.images is None:
            raise PlanningError(f"the planned policy needs the views at step {t} (a history frame) but "
                                f"got none; drive it with run_episode or render when wants_images(t) is true")
        self.frames[t] = (self.encode(obs.images), torch.as_tensor(obs.proprio, device=self.device))
        self.seen.add(t)
        # nothing older is needed again; an imagined history may roll from the frame seen a chunk or two before
        oldest = t - (self.context - 1) * self.frameskip - (self.period if self.imagine is None else 2 * self.chunk)
        self.frames = {s: f for s, f in self.frames.items() if s >= oldest}
        self.seen = {s for s in self.seen if s >= oldest}

    def record_action(self, action: np.ndarray) -> None:
        """Keep the (A,) action executed at the next step, clipped to [-1, 1] as the env runs it."""
        self.executed.append(np.clip(action, -1, 1))

    def actions(self, start: int, stop: int) -> torch.Tensor:
        """The actions executed from step ``start`` to ``stop`` (exclusive) -> (L, A) float32 on the device."""
        return torch.from_numpy(np.stack(self.executed[start:stop]).astype(np.float32)).to(self.device)  # (L, A)

    def planning_context(self, t: int) -> PlanningContext | None:
        """History frames at t-(Tc-1)Δ .. t and the action blocks between them; None when the history reaches
        before step 0 (the chunk then runs open loop), or a rest-state history with ``rest_state``."""
        if self.steps(t)[0] < 0 and not self.rest_state:
            return None
        return self._context(t)

    def _context(self, t: int) -> PlanningContext:
        """The context of step t: its history frames (imagined where unseen, with ``imagine``); steps before 0 are
        the rest state with ``rest_state``, else left out (the context is shorter: what imagining from step 0
        starts from)."""
        steps = self.steps(t)
        if not self.rest_state:
            steps = [s for s in steps if s >= 0]
        if self.imagine is not None:
            for s in steps:
                if 0 <= s < t and s not in self.frames:  # the frame of t itself is always seen
                    self._imagine_until(s)
        missing = [s for s in steps if s >= 0 and s not in self.frames]
        if missing:
            raise PlanningError(f"history frames at steps {missing} are missing for the chunk at step {t}; the "
                                f"policy must see every step from the episode start (reset it before each episode)")
        # Before step 0 the robot rested: the first frame again, with hold-still actions (arm still, gripper open).
        z = torch.stack([self.frames[max(s, 0)][0] for s in steps])  # (Tc, V, N, D)
        q = torch.stack([self.frames[max(s, 0)][1] for s in steps])  # (Tc, P)
        dim = len(self.executed[0]) if self.executed else len(self.hold_action)  # A
        acts = np.zeros((t - steps[0], dim), np.float32)  # ((Tc-1)Δ, A)
        for i, s in enumerate(range(steps[0], t)):
            acts[i] = self.executed[s] if s >= 0 else self.hold_action
        a = torch.from_numpy(acts.reshape(len(steps) - 1, self.frameskip * dim)).to(self.device)  # (Tc-1, Δ·A)
        return PlanningContext(z, q, a)

    def _imagine_until(self, step: int) -> None:
        """Predict the frames Δ, 2Δ, ..., up to ``step`` after the latest frame seen before it on its grid (the last
        planning point's, as a rule), in one rollout from that frame's context under the actions executed since; keep
        those not kept yet."""
        start = max((s for s in self.seen if s < step and (step - s) % self.frameskip == 0), default=None)
        if start is None:
            raise PlanningError(f"no frame before step {step} to imagine it from; the policy must see the planning "
                                f"points' frames from the episode start (reset it before each episode)")
        z, q = self.imagine(self._context(start), self.actions(start, step))  # (S, V, N, D), (S, P)
        for i in range(len(z)):
            self.frames.setdefault(start + (i + 1) * self.frameskip, (z[i].to(self.device), q[i].to(self.device)))
