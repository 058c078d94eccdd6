"""The planning proxy: ``POST /act`` (and ``/s/<robot>/act``) forwards each request to the upstream WAM, plans
its chunk in a world model toward the upstream's predicted views (``PlannedPolicy.plan_chunk``, as condition 7
plans), and answers in the upstream's own format: the planned chunk in ``actions`` (the task's columns of the
upstream's actions replaced), the upstream's other fields passed through, and a ``wamplan`` field (session,
episode step, whether the chunk was planned or why it ran open loop, costs, timings, notes).

What a request may add for the proxy (all optional; none is forwarded to the upstream):

* ``session_id`` (RoboArena-style): with the URL's robot, names the session; ``reset: true`` starts a new
  episode; ``seed`` (int, read when an episode starts): the planner's episode seed;
* ``executed_actions`` ((H, A), LingBot-VA-style): what the robot ran of the chunk answered last (default: that
  chunk, whole); ``chunk_frames``: the frames the robot saw during that chunk, ``{"<offset>": {<image fields>,
  "proprio": (P,)}}`` with offsets 1..H-1 from the chunk's start. A learned world model needs a frame every Δ
  steps (Δ = its frameskip; 4 for the shipped one): without those frames a chunk is answered open loop with the
  reason ``no-history``. One whose Δ is the chunk needs none: the boundaries the robot posts are its frames.

Upstream's eval client's ``proprio_history`` (N proprio vectors) / ``images_history`` (N left-wrist, N right-wrist,
then N primary images, each oldest first; ALOHA's fields) are forwarded to the upstream untouched; their frames,
``history_spacing`` steps apart and ending one spacing before the boundary, also join the world model's history
where they fall on its frames (with the shipped Δ=4 model and upstream's spacing of 12 they never do).
A chunk runs the upstream's own chunk (open loop, the ``wamplan`` field says why) on the first chunk of an
episode, on a history that reaches before the episode, without the frames above (``no-history``), when planning
takes longer than ``budget_ms`` (``over-budget``; the plan finishes in the background before the session's
next request), when the planner's gates say so, or when planning fails (``planning-failed``, logged).
Failures of the request or the upstream are answered in the error mode (``wamplan.serving.ERROR_MODES``).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from typing import Any, Callable

import numpy as np
from fastapi import FastAPI, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response

from wamplan.envs.spec import Observation, TaskSpec
from wamplan.errors import UserError, reason
from wamplan.proxy.config import DEFAULT_ROBOT, PROXY_FIELDS, ProxyConfig
from wamplan.proxy.openpi import add_openpi_routes
from wamplan.proxy.sessions import BadRequest, Session, Sessions, session_name
from wamplan.proxy.health import UpstreamHealth
from wamplan.proxy.upstream import AnsweredWAM, Upstream, UpstreamError, UpstreamShape, answer_shape, to_output
from wamplan.serving import HEALTH_ROUTE
from wamplan.serving.refusals import Refused, check_secret, error_answer, read_body
from wamplan.wam import protocol

log = logging.getLogger(__name__)

SESSION_ROUTE = "/s/{robot}/act"
RESET_ROUTE = "/s/{robot}/reset"


def _seed(seed: Any) -> int | None:
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer))):
        raise BadRequest(f"seed is {seed!r}, expected an integer")
    return None if seed is None else int(seed)


def _finite(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def planning_grid(requery: int, dynamics: Any) -> int:
    """The steps apart that a session's requests can be planned from: a client asks every ``requery`` steps, a
    learned world model's frames are its frameskip apart (their gcd); any step for dynamics without history."""
    if not getattr(dynamics, "needs_history", False):
        return 1
    return math.gcd(requery, getattr(dynamics, "frameskip", requery))


class Proxy:
    """The proxy's state: the upstream, the shared world model, the sessions. ``handle`` answers one request."""

    def __init__(self, cfg: ProxyConfig, upstream: Upstream, dynamics: Any, encoder: Any, task: TaskSpec,
                 make_policy: Any, request_map: dict[str, str], response_map: dict[str, str],
                 columns: tuple[int, ...], chunk_length: int, requery: int | None = None,
                 probe: tuple[protocol.ActRequest, Observation] | None = None,
                 fit: Callable[[UpstreamShape], None] | None = None, imagined: bool = False):
        """``requery``: the steps a client that sends no ``executed_actions`` runs of each chunk (default: all);
        ``imagined``: the sessions' policies imagine the in-chunk history frames (``--history imagined``);
        ``probe``: the rest observation the start-up check and ``/health`` send the upstream; ``fit``: the check
        that refuses an upstream the world model cannot plan for (UserError), run on its first answer where the
        start-up probe got none."""
        self.cfg, self.upstream, self.dynamics, self.encoder, self.task = cfg, upstream, dynamics, encoder, task
        self.request_map, self.response_map, self.columns = request_map, response_map, columns
        self.chunk = chunk_length
        self.cameras = tuple(response_map)
        self.frameskip = getattr(dynamics, "frameskip", chunk_length)
        self.requery = requery or chunk_length  # K: what a client that says nothing runs of a chunk
        self.grid = planning_grid(self.requery, dynamics)
        self.imagined = imagined
        self._probe, self._fit = probe, fit
        self.fit_checked = fit is None  # whether the fit check has seen an answer of the upstream
        self.health = UpstreamHealth(upstream, self.probe)
        self.model_lock = threading.Lock()  # the world model and encoder are shared: one user at a time
        self.planner_pool = ThreadPoolExecutor(max_workers=4, thread_name_prefix="wamplan-plan")
        self._make_policy = make_policy
        self.recorder = None  # `serve --record DIR`: every session written as episodes (proxy.record)
        if cfg.record:
            from wamplan.proxy.record import Recorder

            self.recorder = Recorder(cfg.record, task, tuple(request_map.values()), chunk_length, cfg.record_every)
        self.sessions = Sessions(self._session, cfg.idle_s, cfg.max_sessions, on_forget=self._forgotten)

    def _forgotten(self, session: Session, why: str) -> None:
        if self.recorder is not None:
            self.recorder.end(session, why)

    def _session(self, key: str) -> Session:
        wam = AnsweredWAM(self.task, self.chunk, self.cameras)
        return Session(key, self._make_policy(wam), wam)

    def describe(self) -> str:
        """What the proxy plans for, in three lines: the fields and sizes, the history its world model needs, and
        how it follows a client that runs part of each chunk."""
        H, d, K = self.chunk, self.frameskip, self.requery
        if not getattr(self.dynamics, "needs_history", False):
            history = "history: none (the dynamics need no frames)"
        elif d == H:
            history = (f"history: chunk boundaries only (the world model's frameskip {d} is the chunk): the "
                       f"observations a client posts are its frames")
        elif self.imagined:
            history = (f"history: chunk boundaries only: the world model's frames every {d} steps inside a chunk are "
                       f"imagined from the last boundary and the actions run since (--history imagined); "
                       f"frames a client sends in chunk_frames are used instead")
        else:
            offsets = ", ".join(str(o) for o in range(d, H, d)) or "-"
            history = (f"history: in-chunk frames every {d} steps (the world model's frameskip {d}, not the {H}-step "
                       f"chunk): send the frames seen during a chunk in chunk_frames (offsets {offsets}), else its "
                       f"chunks run open loop (no-history; --history imagined plans them from the boundaries)")
        partial = (f"partial chunks: a client that runs k < {H} steps before asking again is followed (executed_"
                   f"actions of k rows; one that sends none runs {K}, --requery-every); a chunk is planned when the "
                   f"request falls on the world model's grid of {self.grid} steps, else answered open loop "
                   f"(off-grid)")
        return (f"{protocol.field_map(self.request_map, self.response_map)}; chunks of {H}, task "
                f"{self.task.name} action columns {list(self.columns)}; world model frameskip {d}; "
                f"{protocol.proprio_rule(self.task.proprio_dim, self.cfg.fit_proprio)}\n{history}\n{partial}")

    def probe(self) -> None:
        """Send the upstream the rest observation and check its answer (UpstreamError: no answer, or one the world
        model cannot plan for)."""
        if self._probe is None:
            return
        req, obs = self._probe
        self._checked(self.upstream.ask(req, obs))

    def _checked(self, ans: protocol.ActResponse) -> protocol.ActResponse:
        """``ans`` once the fit check has seen an answer (the first time: this one; a misfit is an UpstreamError
        every request and ``/health`` report)."""
        if not self.fit_checked and self._fit is not None:
            try:
                self._fit(answer_shape(ans))
            except UserError as e:
                raise UpstreamError(502, str(e)) from e
            self.fit_checked = True
        return ans

    def close(self) -> None:
        self.planner_pool.shutdown(wait=False, cancel_futures=True)
        self.upstream.close()
        if self.recorder is not None:
            self.recorder.close()  # the episodes in progress written whole

    def reset(self, robot: str) -> int:
        """Forget the sessions of ``robot`` (with any session_id) -> how many there were."""
        keys = [k for k in self.sessions.keys() if k == robot or k.startswith(robot + "/")]
        return sum(self.sessions.drop(k) for k in keys)

    # ------------------------------------------------------------------ one request
    def handle(self, body: bytes, robot: str = DEFAULT_ROBOT) -> str:
        """One ``/act`` body (json_numpy) -> the answer's JSON text."""
        t_in = time.perf_counter()
        req = protocol.decode_request(body, tuple(self.request_map))
        return protocol.encode_response(self.respond(req, robot, t_in=t_in), double_encode=req.encoded)

    def respond(self, req: protocol.ActRequest, robot: str = DEFAULT_ROBOT, key: str | None = None,
                t_in: float | None = None) -> protocol.ActResponse:
        """One checked request -> the answer. Its session: ``<robot>/<session_id>`` when it names one, else
        ``key`` (default: ``robot``)."""
        t_in = time.perf_counter() if t_in is None else t_in
        ours = {k: req.extra.pop(k) for k in PROXY_FIELDS if k in req.extra}
        sid = session_name(ours.get("session_id"))
        key = (key or robot) if sid is None else f"{robot}/{sid}"
        session, why = self.sessions.get(key)
        with session.lock:
            self._settle(session)
            if ours.get("reset"):
                why = "reset"
            seed = _seed(ours.get("seed"))
            notes: list[str] = []
            if why in ("idle", "reset") or (why == "first-request" and seed is not None):
                session.new_episode(seed or 0)
            elif session.chunks:
                self._catch_up(session, ours, notes)
            if session.chunks:
                self._upstream_history(session, req)
            why, session.announce = why or session.announce, None
            return self._answer(session, req, why, notes, t_in)

    def restart(self, key: str, seed: Any = None) -> None:
        """Start a new episode in session ``key`` now (RoboArena's ``endpoint: reset``); the next answer's
        ``new_episode`` says ``reset``."""
        seed = _seed(seed)
        session, _ = self.sessions.get(key)
        with session.lock:
            self._settle(session)
            if self.recorder is not None:
                self.recorder.end(session, "reset")
            session.new_episode(seed or 0)
            session.announce = "reset"

    def summary(self) -> dict[str, Any]:
        """What ``GET /health`` and the WebSocket's metadata say about the proxy."""
        return {"upstream": self.upstream.where, "task": self.task.name, "chunk_length": self.chunk,
                "action_dim": self.upstream.shape.action_dim or len(self.columns), "cameras": list(self.cameras),
                "world_model": self.cfg.world_model}

    def _settle(self, session: Session) -> None:
        """A plan that ran past its budget finishes before the session's next request is read."""
        if session.pending is not None:
            try:
                session.pending.result()
            except Exception:  # it was answered open loop already; its failure is only logged
                log.exception("a plan past its budget failed (session %s)", session.key)
            session.pending = None

    def _catch_up(self, session: Session, ours: dict[str, Any], notes: list[str]) -> None:
        """Record what the robot ran of the chunk answered last (``executed_actions``: k <= H rows; none sent: the
        first ``requery`` actions answered), and the frames it saw meanwhile; the session's next step is k on."""
        H, prev = self.chunk, session.last
        acts = ours.get("executed_actions")
        if acts is None:
            acts = session.answered[:self.requery]  # (K, A)
        else:
            acts = np.asarray(acts, dtype=np.float32)
            if acts.ndim != 2 or not 1 <= acts.shape[0] <= H or not np.isfinite(acts).all():
                raise BadRequest(f"executed_actions has shape {acts.shape} or non-finite values; send the k actions "
                                 f"(1 <= k <= {H}) the robot ran of the last chunk, one row each")
            if acts.shape[1] != len(self.columns):
                if acts.shape[1] <= max(self.columns):
                    raise BadRequest(f"executed_actions has {acts.shape[1]} columns; send the task's "
                                     f"{len(self.columns)} or the upstream's")
                acts = acts[:, list(self.columns)]  # (k, A)
        H = len(acts)  # the steps run since the last answer: chunk_frames' offsets are 1..k-1
        session.step = prev + H
        if self.recorder is not None and ours.get("executed_actions") is not None:
            self.recorder.ran(session, acts)
        history = session.policy.history
        del history.executed[prev:]  # a request retried after a failure recorded them already
        for a in acts:
            history.record_action(a)
        frames = ours.get("chunk_frames") or {}
        if not isinstance(frames, dict):
            raise BadRequest("chunk_frames must map step offsets ('1'..) to frames {<image fields>, 'proprio'}")
        for off in sorted(frames, key=lambda k: int(k) if str(k).isdigit() else -1):
            if not str(off).isdigit() or not 0 < int(off) < H:
                raise BadRequest(f"chunk_frames offset {off!r} is not in 1..{H - 1} (the robot ran {H} steps since "
                                 f"the last answer)")
            obs = self._observation(frames[off], prev + int(off), f"chunk_frames[{off}]")
            if self.recorder is not None:
                self.recorder.frame(session, obs)
            with self.model_lock:
                history.observe(obs)

    def _upstream_history(self, session: Session, req: protocol.ActRequest) -> None:
        """The frames of upstream's ``proprio_history`` / ``images_history`` that the world model's history keeps."""
        q, views = req.extra.get("proprio_history"), req.extra.get("images_history")
        fields = protocol.REQUEST_IMAGE_FIELDS  # upstream's eval client orders them left, right wrist, primary
        if q is None or views is None or set(self.request_map) != set(fields):
            return
        n = len(q)
        if not isinstance(views, list) or len(views) != 3 * n:
            raise BadRequest(f"images_history holds {len(views) if isinstance(views, list) else views!r} images "
                             f"for {n} proprio_history entries; upstream's client sends 3 per entry")
        order = ("left_wrist_image", "right_wrist_image", "primary_image")
        history, t = session.policy.history, session.step
        for i in range(n):
            step = t - (n - i) * self.cfg.history_spacing
            if step < 0 or step in history.frames or not history.wants(step):
                continue
            frame = {name: views[k * n + i] for k, name in enumerate(order)}
            obs = self._observation({**frame, "proprio": q[i]}, step, f"images_history[{i}]")
            with self.model_lock:
                history.observe(obs)

    def _check_views(self, req: protocol.ActRequest) -> None:
        """Refuse request views far smaller than the world model reads (less than half its side): it would plan
        from a blur."""
        size = getattr(self.encoder, "input_size", None)
        for name, img in req.images.items():
            h, w = img.shape[:2]
            if size and min(h, w) < size / 2:
                raise BadRequest(f"request field '{name}' is a {h}x{w}-px view; the world model reads {size}-px "
                                 f"views: send the camera's image at {size} px or more")

    def _proprio(self, proprio: np.ndarray) -> tuple[np.ndarray, str | None]:
        """(P,) -> (the world model's P,) and a note: refused (BadRequest) unless --fit-proprio."""
        try:
            return protocol.fit_proprio(proprio, self.task.proprio_dim, self.cfg.fit_proprio)
        except protocol.ProtocolError as e:
            raise BadRequest(f"world model: {e}") from None

    def _observation(self, frame: Any, step: int, what: str) -> Observation:
        if not isinstance(frame, dict):
            raise BadRequest(f"{what} is a {type(frame).__name__}, expected {{<image fields>, 'proprio'}}")
        missing = [k for k in (*self.request_map, "proprio") if k not in frame]
        if missing:
            raise BadRequest(f"{what} lacks {missing}")
        images = {cam: protocol.as_image(frame[name], f"{what}['{name}']") for name, cam in self.request_map.items()}
        q = protocol.as_numbers(frame["proprio"], f"{what}['proprio']", ndim=1)  # (P,)
        return Observation(step=step, proprio=self._proprio(q)[0], images=images)

    def _answer(self, session: Session, req: protocol.ActRequest, why: str | None, notes: list[str],
                t_in: float) -> protocol.ActResponse:
        t, H = session.step, self.chunk
        self._check_views(req)
        proprio, note = self._proprio(req.proprio)  # (P,) what the world model reads
        notes += [f"world model: {note}"] if note else []
        obs = Observation(step=t, proprio=proprio, images={cam: req.images[f] for f, cam in self.request_map.items()})
        forward = dataclasses.replace(req, encoded=False)  # the proxy decodes the answer itself
        t0 = time.perf_counter()
        try:
            ans = self._checked(self.upstream.ask(forward, obs))
            if ans.actions.shape[0] != H:
                raise UpstreamError(502, f"{self.upstream.where} returned a {ans.actions.shape[0]}-step chunk; the "
                                         f"proxy was started for {H}-step chunks")
            out, more = to_output(ans, self.task, self.response_map, self.columns)
        except UpstreamError as e:
            self.health.failed(e, "/act")
            raise
        self.health.record(True, "it answered /act", "/act")
        upstream_s = time.perf_counter() - t0
        notes += more
        t1 = time.perf_counter()
        executed, open_loop, costs = self._decide(session, obs, out, notes)
        plan_s = time.perf_counter() - t1
        session.answered = np.clip(executed, -1.0, 1.0).astype(np.float32)  # (H, A) what the robot will run
        if self.recorder is not None:
            self.recorder.boundary(session, obs, session.answered, session.seed)
        session.last, session.step, session.chunks = t, t + self.requery, session.chunks + 1
        actions = ans.actions.copy()  # (H, A_upstream): the upstream's own chunk when open loop
        if open_loop is None:
            actions[:, list(self.columns)] = executed
        report = {"session": session.key, "step": t, "new_episode": why, "planned": open_loop is None,
                  "open_loop": open_loop, "costs": costs,
                  "timings_s": {"upstream": upstream_s, "plan": plan_s, "total": time.perf_counter() - t_in}}
        if ans.wamplan:
            report["upstream"] = ans.wamplan
        if notes:
            report["notes"] = notes
        return protocol.ActResponse(actions=actions, future_images=ans.future_images, value=ans.value,
                                    extra=ans.extra, wamplan=report)

    def _decide(self, session: Session, obs: Observation, out: Any,
                notes: list[str]) -> tuple[np.ndarray, str | None, dict[str, float | None]]:
        """-> (the (H, A) chunk to run, why it is the upstream's own (None: planned), costs)."""
        policy, t = session.policy, obs.step
        history = policy.history
        if t % self.grid:  # the robot ran a part of the chunk that leaves it between the world model's frames
            # (an imagined history needs the robot's steps on the frames' grid: --history seen where they are not)
            seen = " --history seen" if self.imagined and (t - session.last) % self.frameskip else ""
            notes.append(f"the robot ran {t - session.last} steps of the last chunk, so this request (step {t}) falls "
                         f"off the steps the world model plans from (every {self.grid}: its frames {self.frameskip} "
                         f"apart, clients asking every {self.requery}); start serve with --requery-every "
                         f"{t - session.last}{seen} if the robot always runs that many")
            return out.actions, "off-grid", {}
        if history.keeps_frames and history.imagine is None and t > 0 and (history.real(t) or history.rest_state):
            missing = [s for s in history.steps(t) if 0 <= s < t and s not in history.frames]
            if missing:
                with self.model_lock:
                    history.observe(obs)
                notes.append(f"the world model needs the frames at steps {missing} (one every {self.frameskip} steps "
                             f"before step {t}); send the frames seen during each chunk in chunk_frames")
                return out.actions, "no-history", {}
        session.wam.answer(out)
        if policy.open_loop_rule(t) is not None:  # no search: no budget to keep
            with self.model_lock:
                decision = policy.plan_chunk(obs)
            return decision.executed, decision.reason, {}

        def plan():
            with self.model_lock:
                decision = policy.plan_chunk(obs)
                del policy.chunks[:-4]  # records are for diagnostics only: keep memory bounded
                return decision

        budget = self.cfg.budget_ms / 1000.0
        try:
            if budget > 0:
                future = self.planner_pool.submit(plan)
                try:
                    decision = future.result(timeout=budget)
                except FutureTimeout:
                    session.pending = future
                    notes.append(f"planning took longer than the {self.cfg.budget_ms:g} ms budget")
                    return out.actions, "over-budget", {}
            else:
                decision = plan()
        except Exception as e:  # planning must not cost the robot its chunk
            log.exception("planning failed (session %s, step %d)", session.key, t)
            notes.append(f"planning failed ({reason(e)}); the server's log has the traceback")
            return out.actions, "planning-failed", {}
        c = decision.costs
        costs = {"wam": _finite(c.seed), "best": _finite(c.best), "plan": _finite(c.plan)}
        return decision.executed, decision.reason, costs


def create_proxy_app(proxy: Proxy, secret: str | None = None) -> FastAPI:
    """The HTTP face of ``proxy``: ``POST /act``, ``POST /s/<robot>/act``, ``POST /s/<robot>/reset``,
    ``GET /health``, and openpi's WebSocket on ``/`` and ``/s/<robot>`` (``proxy.openpi``); ``secret`` as
    ``wamplan wam serve`` takes it (header, bearer, api-key or ``?token=``)."""
    cfg, secret = proxy.cfg, secret or None
    app = FastAPI(title="wamplan planning proxy")

    async def act(request: Request, robot: str) -> Response:
        route = request.url.path
        try:
            check_secret(request, secret)
            body = await read_body(request, cfg.max_request_bytes)
        except Refused as r:
            return error_answer(cfg.errors, r.status, r.message, route)
        try:
            content = await run_in_threadpool(proxy.handle, body, robot)
        except protocol.ProtocolError as e:
            return error_answer(cfg.errors, 400, f"bad /act request: {e}", route)
        except UpstreamError as e:
            return error_answer(cfg.errors, e.status, e.message, route)
        except UserError as e:
            return error_answer(cfg.errors, 422, str(e), route)
        except Exception as e:
            log.exception("%s failed", route)
            return error_answer(cfg.errors, 500, f"the proxy failed on this request ({reason(e)}); its log has the "
                                                 f"traceback", route)
        return Response(content=content, media_type="application/json")

    @app.post(protocol.ROUTE)
    async def act_default(request: Request) -> Response:
        return await act(request, DEFAULT_ROBOT)

    @app.post(SESSION_ROUTE)
    async def act_session(robot: str, request: Request) -> Response:
        return await act(request, robot)

    @app.post(RESET_ROUTE)
    async def reset(robot: str, request: Request) -> Response:
        try:
            check_secret(request, secret)
        except Refused as r:
            return error_answer(cfg.errors, r.status, r.message, request.url.path)
        n = proxy.reset(robot)
        return Response(content=json.dumps({"ok": True, "sessions_reset": n}), media_type="application/json")

    add_openpi_routes(app, proxy, secret)

    @app.get(HEALTH_ROUTE)
    async def health() -> Response:
        """200 while the upstream answers (as last seen by the start-up probe, an /act or a refresh at most every
        few seconds), else 503 with the reason; no poll waits on the upstream."""
        state = proxy.health.read()
        body = {**state, "proxy": True, **proxy.summary(), "sessions": len(proxy.sessions)}
        return Response(content=json.dumps(body), status_code=200 if state["ok"] else 503,
                        media_type="application/json")

    return app
