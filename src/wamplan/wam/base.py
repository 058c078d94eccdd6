"""The world-action-model (WAM) interface (paper §3.1), its registry, and a WAM run as a policy.

A WAM maps the current observation ``o_t = (q_t, I_t)`` and a language instruction to an action chunk
``a_{t:t+H-1}`` (H = ``chunk_length``) AND the images it expects at ``t + H`` for each camera:

    out = wam.predict(obs, "insert the cube into the hole")
    out.actions          # (H, A) float32 in [-1, 1]
    out.images["front"]  # (h, w, 3) uint8, the predicted view at t + H

Implementations register with ``@register_wam(name)`` and are built with ``make_wam(name, **kw)``;
trained ones also register a checkpoint loader with ``@register_wam_loader(kind)`` so that
``load_wam(path)`` can dispatch on the checkpoint's kind. :class:`WAMPolicy` executes each chunk open
loop and re-queries the WAM every H steps: the no-planning baseline.
"""

from __future__ import annotations

import abc
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, ClassVar

import numpy as np

from wamplan.envs.spec import Observation, TaskSpec, check_same_task, get_task, require_observation
from wamplan.errors import UserError
from wamplan.policies.base import Policy
from wamplan.registry import Registry

# Modules that register WAMs or checkpoint loaders; the registries import them when first read.
# Whoever adds a WAM module (TinyWAM, the expert oracle) adds it here.
BUILTIN_WAM_MODULES = ("wamplan.wam.cosmos_client", "wamplan.wam.tinywam", "wamplan.wam.oracle")

# The task of a WAM (or WAM checkpoint) that names none: every one made before tasks acted in it.
from wamplan.envs.spec import DEFAULT_TASK as LEGACY_TASK  # noqa: E402  (what records no task means)
# The cube-insertion task's language instruction (the paper does not quote one); a WAM's default instruction is
# its task's (``TaskSpec.instruction``), which for cube-insertion is this.
DEFAULT_INSTRUCTION = "insert the cube into the square hole"


class WAMError(UserError):
    """A WAM cannot be built, loaded or used; the message names the problem and the fix."""


class WAMOutputError(WAMError):
    """A WAM returned an output that breaks the contract (shape, dtype, finiteness, range)."""


class WAMServerError(WAMError):
    """A remote WAM server is unreachable, failed, or answered something malformed."""


@dataclass
class WAMOutput:
    """One WAM query: the action chunk and the predicted images at the end of the chunk."""

    actions: np.ndarray  # (H, A) float32 in [-1, 1]
    images: dict[str, np.ndarray]  # camera -> (h, w, 3) uint8, predicted observation at t + H
    value: float | None = None  # predicted value of the outcome, when the WAM has a value head
    timing: dict[str, float] = field(default_factory=dict)  # seconds, e.g. {"query_s": 1.2}
    extras: dict[str, Any] = field(default_factory=dict)  # implementation-specific diagnostics


def validate_wam_output(out: WAMOutput, *, chunk_length: int, action_dim: int,
                        cameras: tuple[str, ...], source: str = "WAM") -> WAMOutput:
    """Return ``out`` unchanged if it keeps the contract; otherwise raise :class:`WAMOutputError`.

    Never repairs an output (no silent zeros): a broken chunk must stop the episode loudly.
    """

    def fail(problem: str) -> None:
        raise WAMOutputError(f"{source} returned {problem}; fix the WAM (or its server) so that it returns "
                             f"({chunk_length}, {action_dim}) float32 actions in [-1, 1] and uint8 (h, w, 3) "
                             f"images for {list(cameras)}")

    if not isinstance(out, WAMOutput):
        fail(f"a {type(out).__name__} instead of a WAMOutput")
    a = out.actions
    if not isinstance(a, np.ndarray):
        fail(f"actions of type {type(a).__name__}, not a numpy array")
    if a.shape != (chunk_length, action_dim):
        fail(f"actions of shape {a.shape}, expected ({chunk_length}, {action_dim})")
    if a.dtype != np.float32:
        fail(f"actions of dtype {a.dtype}, expected float32")
    if not np.isfinite(a).all():
        fail(f"non-finite actions ({int((~np.isfinite(a)).sum())} NaN/inf values)")
    if np.abs(a).max() > 1.0:
        fail(f"actions outside [-1, 1] (max |a| = {float(np.abs(a).max()):.4g})")
    if not isinstance(out.images, dict):
        fail(f"images of type {type(out.images).__name__}, not a dict camera -> image")
    missing = [c for c in cameras if c not in out.images]
    if missing:
        fail(f"no image for camera(s) {missing} (got {sorted(out.images)})")
    for cam in cameras:
        img = out.images[cam]
        if not isinstance(img, np.ndarray) or img.ndim != 3 or img.shape[2] != 3 or min(img.shape[:2]) < 1:
            fail(f"a '{cam}' image of shape {getattr(img, 'shape', None)}, expected (h, w, 3)")
        if img.dtype != np.uint8:
            fail(f"a '{cam}' image of dtype {img.dtype}, expected uint8")
    if out.value is not None and not (isinstance(out.value, (int, float, np.floating)) and np.isfinite(out.value)):
        fail(f"value {out.value!r}, expected a finite float or None")
    return out


class _TaskDefault:
    """A settable attribute of a WAM that defaults to its task's field ``field`` (set values pass through ``cast``)."""

    def __init__(self, field: str, cast, doc: str):
        self.field, self.cast, self.__doc__ = field, cast, doc

    def __set_name__(self, owner, name: str) -> None:
        self.key = "_" + name

    def __get__(self, wam, owner=None):
        if wam is None:
            return self
        return wam.__dict__.get(self.key, getattr(wam.task, self.field))

    def __set__(self, wam, value) -> None:
        wam.__dict__[self.key] = self.cast(value)


class WAM(abc.ABC):
    """A world action model. Subclasses set ``name`` (via ``@register_wam``) and may set ``chunk_length``,
    ``task``, ``action_dim``, ``cameras`` and ``default_instruction`` (class attributes, instance attributes or
    properties). ``task`` is the :class:`~wamplan.envs.spec.TaskSpec` the WAM acts in (from its checkpoint or its
    config; a WAM that sets none acts in :data:`LEGACY_TASK`); ``action_dim``, ``cameras`` and
    ``default_instruction`` default to the task's."""

    name: ClassVar[str] = ""
    chunk_length: int = 16  # H: actions per chunk; the images are predicted for t + H

    @property
    def task(self) -> TaskSpec:
        """The task the WAM acts in (its checkpoint's or config's; :data:`LEGACY_TASK` if it sets none)."""
        return get_task(self.__dict__.get("_task", LEGACY_TASK))

    @task.setter
    def task(self, task: str | TaskSpec) -> None:
        self._task = get_task(task)

    action_dim = _TaskDefault("action_dim", int, "A, the size of one action (default: the task's)")
    cameras = _TaskDefault("cameras", tuple, "the cameras the WAM reads and predicts, in order (default: the task's)")
    default_instruction = _TaskDefault("instruction", str, "what WAMPolicy sends when given no instruction (default: "
                                                            "the task's instruction)")

    @abc.abstractmethod
    def predict(self, obs: Observation, instruction: str) -> WAMOutput:
        """The chunk and predicted images for ``obs`` (which carries images for ``self.cameras``)."""

    frame_offsets: tuple[int, ...] = ()  # in-chunk step offsets (1..H-1) whose observations observe() takes

    def reset(self) -> None:
        """Start a new episode (clear any internal state, e.g. a history of frames)."""

    def begin_episode(self, seed: int | None = None) -> None:
        """Start episode ``seed``: what the policies driving a WAM call. Default: :meth:`reset`, for a WAM that
        needs no seed."""
        self.reset()

    def observe(self, obs: Observation) -> None:
        """The observation (with images) at an in-chunk step whose offset is in ``frame_offsets``; the policy
        driving the WAM calls it before the next chunk's :meth:`predict`. Default: no offsets, never called."""

    def close(self) -> None:
        """Release resources (network sessions, worker processes)."""

    def validate(self, out: WAMOutput) -> WAMOutput:
        """``validate_wam_output`` against this WAM's own shape contract."""
        return validate_wam_output(out, chunk_length=self.chunk_length, action_dim=self.action_dim,
                                   cameras=tuple(self.cameras), source=f"WAM '{self.name}'")

    def config_dict(self) -> dict[str, Any]:
        """The WAM's configuration, stored as provenance with evaluation results."""
        return {"name": self.name}


WAMS = Registry("WAM", set_name=True, modules=BUILTIN_WAM_MODULES, error=WAMError)
register_wam = WAMS.register  # class decorator: make a WAM constructible by name (``make_wam``)
WAM_LOADERS = Registry("WAM checkpoint kind", modules=BUILTIN_WAM_MODULES)
# decorator: ``fn(path, device) -> WAM`` loads checkpoints whose ``config.json`` has ``"kind": kind``
register_wam_loader = WAM_LOADERS.register


def make_wam(name: str, **kwargs: Any) -> WAM:
    """Build the WAM registered as ``name``."""
    return WAMS.lookup(name)(**kwargs)


def load_wam(path: str | Path, device: str | Any = "auto") -> WAM:
    """Load a WAM checkpoint directory (or a training run holding one in ``checkpoint/``) onto ``device``
    ('auto', 'cpu', 'cuda', a torch.device), dispatching on its kind (see ``register_wam_loader``)."""
    import os

    from wamplan.checkpoint import CheckpointError, checkpoint_dir, read_meta  # imports torch

    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"load_wam's path takes a WAM checkpoint directory (a str or Path), got {type(path).__name__} "
                        f"{path!r}; e.g. load_wam('checkpoints/mini/tinywam')")
    p = checkpoint_dir(path)
    kind = read_meta(p).get("kind")  # one line for a missing, damaged or foreign config.json
    if kind not in WAM_LOADERS:
        known = sorted(WAM_LOADERS) or "none registered yet"
        raise CheckpointError(f"{p} holds a '{kind}' checkpoint, which is not a WAM (WAM kinds: {known}); "
                              f"pass a WAM checkpoint directory instead (e.g. from `wamplan wam train`)")
    return WAM_LOADERS[kind](p, device=device)


class WAMPolicy(Policy):
    """A WAM as a policy: query at steps 0, H, 2H, ... and execute each chunk open loop.

    ``refine(obs, out) -> (H, A) actions``, if given, replaces each proposed chunk before it is executed
    (the planner's hook); the WAM's own output stays available as ``last_output``. Without an
    ``instruction`` the WAM's ``default_instruction`` is sent. Executed actions are
    clipped to [-1, 1], the range every policy promises. ``task`` is the task of the env the policy acts in
    (``env.task``; None: the WAM's own): a WAM made for another task, or one whose actions are not that task's
    size, is one line. Not in the policy registry: it needs a WAM (``WAMPolicy(load_wam(path))``), so a name
    alone cannot build it.
    """

    name = "wam"

    def __init__(self, wam: WAM, instruction: str | None = None,
                 refine: Callable[[Observation, WAMOutput], np.ndarray] | None = None,
                 task: str | TaskSpec | None = None):
        task = get_task(task) if task is not None else wam.task
        check_same_task(task.name, wam.task.name, f"WAM '{wam.name}'",
                        f"act in task '{wam.task.name}' (make_env(task='{wam.task.name}')) or use a WAM made for "
                        f"'{task.name}'")
        self.task = task  # the task of the env it acts in
        if wam.action_dim != task.action_dim:
            raise WAMError(f"WAM '{wam.name}' outputs {wam.action_dim}-D actions but task {task.name} takes "
                           f"{task.action_dim}-D ones; configure the WAM's action dimensions")
        self.wam = wam
        self.instruction = instruction if instruction is not None else wam.default_instruction
        self.refine = refine
        self.reset()

    @property
    def chunk_length(self) -> int:
        return int(self.wam.chunk_length)

    def reset(self, seed: int | None = None) -> None:
        self.wam.begin_episode(seed)
        self.last_output: WAMOutput | None = None  # the WAM's latest proposal (planner target, diagnostics)
        self.current_chunk: np.ndarray | None = None  # (H, A) the chunk being executed
        self._index = 0  # next row of current_chunk
        self._query_steps: list[int] = []
        self._query_s: list[float] = []
        self._refine_s: list[float] = []
        self._proxy: Counter[str] = Counter()  # a planning proxy's reports: "planned" or why a chunk ran open loop

    def wants_images(self, step: int) -> bool:
        return step % self.chunk_length == 0 or step % self.chunk_length in self.wam.frame_offsets

    def act(self, obs: Observation) -> np.ndarray:
        require_observation(obs, "WAMPolicy.act")
        if obs.step % self.chunk_length in self.wam.frame_offsets:
            self.wam.observe(obs)
        if self.current_chunk is None or self._index >= self.chunk_length:
            self._start_chunk(obs)
        assert self.current_chunk is not None
        action = self.current_chunk[self._index].copy()  # (A,)
        self._index += 1
        return action

    def _start_chunk(self, obs: Observation) -> None:
        H = self.chunk_length
        if obs.step % H != 0:
            raise WAMError(f"WAMPolicy starts a chunk at step {obs.step}, not a multiple of {H}; "
                           f"call reset() at the start of every episode and act() once per step")
        if obs.images is None:
            raise WAMError(f"the observation at step {obs.step} carries no images but the WAM needs them; "
                           f"render images whenever policy.wants_images(step) is True")
        t0 = time.perf_counter()
        out = self.wam.validate(self.wam.predict(obs, self.instruction))
        self._query_s.append(time.perf_counter() - t0)
        self._query_steps.append(obs.step)
        if "proxy" in out.extras:
            proxy = out.extras["proxy"]
            self._proxy["planned" if proxy["planned"] else str(proxy.get("open_loop") or "unknown")] += 1
        chunk = out.actions  # (H, A)
        if self.refine is not None:
            t1 = time.perf_counter()
            chunk = np.asarray(self.refine(obs, out), dtype=np.float32)  # (H, A)
            self._refine_s.append(time.perf_counter() - t1)
            if chunk.shape != out.actions.shape or not np.isfinite(chunk).all():
                raise WAMError(f"the refined chunk has shape {chunk.shape} or non-finite values; the refine "
                               f"hook must return finite ({H}, {self.wam.action_dim}) actions")
        self.last_output = out
        self.current_chunk = np.clip(chunk, -1.0, 1.0).astype(np.float32)  # (H, A)
        self._index = 0

    def info(self) -> dict[str, Any]:
        info: dict[str, Any] = {"wam": self.wam.name, "chunks": len(self._query_s),
                                "query_steps": list(self._query_steps), "wam_query_s": list(self._query_s)}
        if self.refine is not None:
            info["refine_s"] = list(self._refine_s)
        if self._proxy:  # chunks counted by what the planning proxy did: {"planned": n, <open-loop reason>: n}
            info["proxy"] = dict(self._proxy)
        return info

    def config_dict(self) -> dict[str, Any]:
        return {"name": self.name, "wam": self.wam.config_dict(), "instruction": self.instruction,
                "chunk_length": self.chunk_length, "refined": self.refine is not None}
