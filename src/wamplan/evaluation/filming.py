"""Filming one evaluation episode: a hook of the evaluation runner (``EvalWorker``), never of the planner.

:class:`EpisodeFilm` is a ``run_episode`` hook (``on_obs``, ``images_at``). It keeps the views of every step that
comes with images (the steps the policy renders anyway: chunk boundaries, a world model's history frames; and every
``video_every`` steps when asked), renders the last step once if it came without, and encodes the views side by
side as VP9/WebM at their real times (20 steps a second), the last picture held a second.

For a planned policy it also keeps, per chunk boundary, what ``wamplan explain`` draws for one chunk
(:mod:`wamplan.evaluation.mechanism`): the views now, the target WAM's predicted views (kept by
:class:`TargetRecorder`, a transparent wrapper of the policy's target WAM), the world model's prediction under the
WAM's chunk and under the plan decoded by a picture decoder (read from the policy's ``last_decision`` and its
dynamics, still prepared for that boundary, on the first step after it) and the real views the chunk reached (the
next boundary's, or the last step's): the plan video, one picture a second. Filming never stops an episode: an
error is kept in ``error`` and the episode runs on unfilmed.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from wamplan.envs.media import encode_webm, resize_view, side_by_side
from wamplan.evaluation.videos import FPS, VideoConfig

HOLD_S = 1  # seconds the last picture of an episode video stays on screen


class TargetRecorder:
    """A WAM that forwards everything to ``inner`` and keeps the images each step's prediction expects
    (``images``: step -> camera -> (h, w, 3) uint8), for the episode under way."""

    def __init__(self, inner: Any):
        self.inner = inner
        self.images: dict[int, dict[str, np.ndarray]] = {}

    def predict(self, obs, instruction: str):
        out = self.inner.predict(obs, instruction)
        self.images[obs.step] = out.images
        return out

    def begin_episode(self, seed: int | None = None) -> None:
        self.images = {}
        self.inner.begin_episode(seed)

    def reset(self) -> None:
        self.images = {}
        self.inner.reset()

    def __getattr__(self, name: str) -> Any:  # everything else is the inner WAM's
        return getattr(self.inner, name)


def record_targets(policy: Any) -> TargetRecorder:
    """Wrap a planned ``policy``'s target WAM (and its seed WAM where that is the same WAM) in a
    :class:`TargetRecorder`, once; its choices are unchanged."""
    if isinstance(policy.target_wam, TargetRecorder):
        return policy.target_wam
    rec = TargetRecorder(policy.target_wam)
    if policy.wam is policy.target_wam:
        policy.wam = rec
    policy.target_wam = rec
    return rec


def draws_model(policy: Any) -> bool:
    """Whether ``policy`` plans in a learned world model whose prediction can be decoded in a hook (a simulator or
    a blend with it would step the env)."""
    from wamplan.planning.dynamics import LearnedDynamics

    return isinstance(getattr(policy, "dynamics", None), LearnedDynamics)


def load_plan_decoder(path: str, policy: Any, task: str, cache: dict[int, Any]):
    """The picture decoder at ``path`` for ``policy``'s encoder's tokens, on its device (loaded once per encoder,
    kept in ``cache``), or None without a path."""
    if not path:
        return None
    from wamplan.worldmodel.decoder import load_decoder

    key = id(policy.encoder)
    if key not in cache:
        cache[key] = load_decoder(path, device=policy.device, encoder=policy.encoder, task=task)
    return cache[key]


class EpisodeFilm:
    """Films one episode of ``policy`` (the task's ``cameras`` side by side, views ``cfg.video_size`` px); with
    ``plan`` the chunk boundaries of a planned policy too, in the views it plans with (``policy.cameras``), the model's
    pictures drawn by ``decoder`` (or left out: None)."""

    def __init__(self, policy: Any, cameras: tuple[str, ...], cfg: VideoConfig, plan: bool = False, decoder=None):
        self.policy, self.cameras, self.cfg = policy, tuple(cameras), cfg
        self.plan_cameras = tuple(policy.cameras) if plan else ()  # the world model's views, in its order
        self.frames: dict[int, dict[str, np.ndarray]] = {}  # step -> camera -> (s, s, 3) uint8
        self.boundaries: list[dict[str, Any]] = []  # per chunk decision: its step, target, model pictures, costs
        self.targets = record_targets(policy) if plan else None
        self.decoder = decoder if plan and draws_model(policy) else None
        self.error: str | None = None
        self._decided: int | None = None  # the step of the latest decision kept

    def images_at(self, step: int) -> bool:
        """``run_episode``'s ``images_at``: the extra frames (every ``video_every`` steps)."""
        return self.cfg.video_every > 0 and step % self.cfg.video_every == 0 and self.error is None

    def __call__(self, env, obs, action) -> None:
        if self.error is not None:
            return
        try:
            if obs.images is not None:
                self.frames[obs.step] = self._small(obs.images)
            if self.targets is not None:
                self._boundary()
        except Exception as e:  # filming never ends an episode; the record keeps it, the video says why not
            self._fail(e)

    def _small(self, views: dict[str, np.ndarray], cameras: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
        """camera -> (H, W, 3) -> camera -> (s, s, 3) uint8 for ``cameras`` (default: the task's)."""
        return {c: resize_view(views[c], self.cfg.video_size) for c in cameras or self.cameras}

    def _fail(self, e: Exception) -> None:
        from wamplan.errors import reason

        self.error = reason(e)
        self.frames, self.boundaries = {}, []

    def _boundary(self) -> None:
        """Keep the policy's latest chunk decision, once, on the first step after it was made."""
        d = self.policy.last_decision
        if d is None or d.step == self._decided:
            return
        self._decided = d.step
        target = self.targets.images.get(d.step)
        kept: dict[str, Any] = dict(step=d.step, reason=d.reason, model={}, cost={},
                                    target=None if target is None else self._small(target, self.plan_cameras))
        if self.decoder is not None and d.plan is not None and d.target is not None:
            from wamplan.evaluation.mechanism import model_pictures

            chunks = {"wam": d.seed, "plan": d.plan}  # (H, A) each
            pics, z = model_pictures(self.policy, self.decoder, chunks)  # (V, S, S, 3) each, (2, V, N, D)
            cost = self.policy.cost(z, d.target)  # (2,) the planning cost (eq. 3) against the WAM's target
            kept["model"] = {k: np.stack([resize_view(v, self.cfg.video_size) for v in pics[k]]) for k in chunks}
            kept["cost"] = {k: float(cost[i]) for i, k in enumerate(chunks)}
        self.boundaries.append(kept)

    def finish(self, env, length: int) -> dict[str, bytes]:
        """After the episode (``length`` steps; ``env`` still at its last state): the encoded videos,
        ``"episode"`` and, for a planned policy, ``"plan"`` (WebM bytes); {} when filming failed (``error``)."""
        if self.error is not None:
            return {}
        try:
            if length not in self.frames:  # the outcome: the last step, rendered once
                self.frames[length] = self._small(env.render(self.cameras))
            steps = sorted(self.frames)
            out = {"episode": encode_webm([side_by_side(self.frames[t], self.cameras) for t in steps], FPS, steps,
                                          hold=HOLD_S * FPS)}
            if self.targets is not None and self.boundaries:
                out["plan"] = self._plan_video(length)
            return out
        except Exception as e:
            self._fail(e)
            return {}

    def _plan_video(self, length: int) -> bytes:
        """One mechanism picture per chunk boundary, a second each."""
        from wamplan.evaluation.mechanism import Mechanism, mechanism_frame

        def views(t: int) -> np.ndarray | None:  # (V, s, s, 3) the views filmed at step t
            return np.stack([self.frames[t][c] for c in self.plan_cameras]) if t in self.frames else None

        pictures = []
        for i, b in enumerate(self.boundaries):
            reached = self.boundaries[i + 1]["step"] if i + 1 < len(self.boundaries) else length
            ran = "wam" if b["reason"] is not None else "plan"
            real = views(reached)
            target = None if b["target"] is None else np.stack([b["target"][c] for c in self.plan_cameras])
            model = b["model"] or ({"wam": None, "plan": None} if self.decoder is not None else {})  # one layout
            m = Mechanism(step=b["step"], now=views(b["step"]), target=target, model=model,
                          real={} if real is None else {ran: real}, model_cost=b["cost"], true_cost={},
                          cube_xy_mm=None, cameras=self.plan_cameras, chunk=self.policy.chunk, reached=reached)
            said = "planned" if b["reason"] is None else f"open loop ({b['reason']})"
            pictures.append(mechanism_frame(m, self.cfg.video_size, title=f"chunk {i}: {said}"))
        return encode_webm(pictures, fps=1, hold=1)
