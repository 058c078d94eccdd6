"""The planning proxy's second front end: openpi's WebSocket protocol (and RoboArena's additions to it).

An unmodified openpi robot client (``openpi_client.websocket_client_policy.WebsocketClientPolicy``) connects to
``ws://HOST:PORT`` (or ``ws://HOST:PORT/s/<robot>``), reads the proxy's metadata (a msgpack dict, sent first), and
then sends one msgpack observation per chunk boundary and reads one msgpack answer: ``actions`` (H, A) float32, the
upstream's other fields, a ``wamplan`` field (as on ``/act``) and openpi's ``server_timing``. Arrays travel in
openpi's msgpack form ``{"__ndarray__": True, "data": bytes, "dtype": str, "shape": [...]}``.

* **One session per connection**: a connection starts an episode and its session is dropped when it closes. A
  message's ``session_id`` (RoboArena) names a session instead (``<robot>/<session_id>``, shared with ``/act``'s,
  kept among the ``--max-sessions`` most recently used).
* **RoboArena's** ``endpoint``: ``"infer"`` (the default) or ``"reset"``, which starts a new episode (with the
  message's ``seed``, if any) and is answered with the text ``reset successful``: the episode of the message's
  ``session_id`` where this connection's observations have named it, else the connection's own.
* **An observation** is read as an ``/act`` request (the same fields, the same proxy fields: ``reset``, ``seed``,
  ``chunk_frames``, ``executed_actions``) after three steps: nested dicts are flattened with ``/`` (openpi's ALOHA
  ``images`` -> ``images/cam_high``); ``--ws-fields`` renames keys (``FROM=TO``; ``A+B=proprio`` joins several
  vectors); openpi's ``prompt`` and ``state`` stand for ``task_description`` and ``proprio`` where those are
  absent. Images may come channels-first (3, H, W), as openpi's ALOHA client sends them. Keys holding ``/`` that no
  rename maps are not forwarded to the upstream.
* **Errors** are a text frame with one line (openpi's client raises it as ``RuntimeError``): the connection stays
  open after a bad message or an upstream failure, and is closed (1011) only after a failure of the proxy itself.
  A missing or wrong secret refuses the connection (HTTP 401); openpi's client sends it as
  ``Authorization: Api-Key SECRET`` (its ``api_key``).
"""

from __future__ import annotations

import itertools
import logging
import time
from typing import Any, Mapping

import msgpack
import numpy as np
from fastapi import FastAPI, WebSocket, WebSocketDisconnect
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import PlainTextResponse

from wamplan.errors import UserError, reason
from wamplan.proxy.config import DEFAULT_ROBOT, PROXY_FIELDS, parse_ws_fields
from wamplan.proxy.sessions import session_name
from wamplan.proxy.upstream import UpstreamError
from wamplan.serving.refusals import Refused, check_secret
from wamplan.wam import protocol

log = logging.getLogger(__name__)

WS_ROUTE, WS_SESSION_ROUTE = "/", "/s/{robot}"
HEALTHZ_ROUTE = "/healthz"  # openpi's server answers GET /healthz
RESET_REPLY = "reset successful"  # RoboArena's server's answer to endpoint: reset
ALIASES = {"prompt": "task_description", "state": "proprio"}  # openpi's names, used where ours are absent
_ARRAY_KEYS = ("__ndarray__", "data", "dtype", "shape")


class BadMessage(protocol.ProtocolError):
    """A WebSocket message that cannot be read as a request."""


# -- openpi's msgpack form of numpy arrays ---------------------------------------------------------------------
def _packable(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind in "VOc":
            raise TypeError(f"cannot send an array of dtype {obj.dtype}")
        return {b"__ndarray__": True, b"data": np.ascontiguousarray(obj).tobytes(), b"dtype": obj.dtype.str,
                b"shape": list(obj.shape)}
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot send a {type(obj).__name__}")


def _array(obj: dict) -> Any:
    """msgpack's object hook: openpi's array dicts (bytes or text keys) -> numpy arrays (writable copies), its
    numpy scalars -> their Python values."""
    d = {k.decode("utf-8", "replace") if isinstance(k, bytes) else k: v for k, v in obj.items()}
    if d.get("__npgeneric__") is True and set(d) == {"__npgeneric__", "data", "dtype"}:
        return d["data"]  # a numpy scalar, sent as its Python value
    if not d.get("__ndarray__"):
        return obj
    try:
        dtype = np.dtype(d["dtype"].decode() if isinstance(d["dtype"], bytes) else d["dtype"])
        if dtype.kind in "VOc":
            raise ValueError(f"dtype {dtype} is not allowed")
        return np.frombuffer(d["data"], dtype=dtype).reshape(d["shape"]).copy()
    except (KeyError, TypeError, ValueError) as e:
        raise BadMessage(f"an array in the message is malformed ({type(e).__name__}: {e}); send openpi's msgpack "
                         f"form {{'__ndarray__': True, 'data', 'dtype', 'shape'}}") from None


def pack(obj: Any) -> bytes:
    """``obj`` (dicts, lists, numbers, strings, numpy arrays) as openpi's msgpack."""
    return msgpack.packb(obj, default=_packable)


def unpack(data: bytes) -> Any:
    """openpi's msgpack -> Python objects with numpy arrays; BadMessage when it is not msgpack."""
    try:
        return msgpack.unpackb(data, object_hook=_array, strict_map_key=False)
    except BadMessage:
        raise
    except (ValueError, TypeError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError) as e:
        raise BadMessage(f"the message is not msgpack ({type(e).__name__}: {e}); send openpi's msgpack") from None


# -- an observation read as an /act request --------------------------------------------------------------------
MAX_NESTING = 8  # dicts nested deeper in an observation are refused


def _flat(d: Mapping, prefix: str = "", depth: int = 0) -> dict[str, Any]:
    if depth >= MAX_NESTING:
        raise BadMessage(f"the observation nests dicts more than {MAX_NESTING} deep (at {prefix!r}); send flat keys")
    out: dict[str, Any] = {}
    for k, v in d.items():
        name = f"{prefix}{k.decode('utf-8', 'replace') if isinstance(k, bytes) else k}"
        if isinstance(v, Mapping) and name not in PROXY_FIELDS:  # chunk_frames keeps its nesting
            out.update(_flat(v, name + "/", depth + 1))
        else:
            out[name] = v
    return out


def _channels_last(x: Any) -> Any:
    if isinstance(x, np.ndarray) and x.ndim in (3, 4) and x.shape[-3] == 3 and x.shape[-1] != 3:
        return np.moveaxis(x, -3, -1)  # (3, H, W) -> (H, W, 3)
    return x


def _renamed(message: Mapping, image_fields: tuple[str, ...], renames: list[tuple[tuple[str, ...], str]],
             what: str, strict: bool = True) -> dict[str, Any]:
    """One observation (or one frame of ``chunk_frames``) flattened, renamed, aliased, its images channels-last;
    ``strict``: a rename whose source keys are missing is refused (else skipped)."""
    obs = _flat(message)
    for sources, dst in renames:
        missing = [s for s in sources if s not in obs]
        if missing and strict:
            raise BadMessage(f"{what} lacks {missing}, which --ws-fields maps to {dst!r} (it has {_keys(obs)})")
        if missing:
            continue
        if len(sources) == 1:
            obs[dst] = obs.pop(sources[0])
            continue
        try:
            parts = [np.asarray(obs.pop(s), dtype=np.float32).reshape(-1) for s in sources]
        except (TypeError, ValueError) as e:
            raise BadMessage(f"{what}: {'+'.join(sources)} cannot be joined into {dst!r} ({_short(e)}); send "
                             f"numeric vectors") from None
        obs[dst] = np.concatenate(parts)
    for theirs, ours in ALIASES.items():
        if ours not in obs and theirs in obs:
            obs[ours] = obs.pop(theirs)
    for name in image_fields:
        if name in obs:
            obs[name] = _channels_last(obs[name])
    return obs


def as_request(message: Mapping, image_fields: tuple[str, ...],
               renames: list[tuple[tuple[str, ...], str]]) -> protocol.ActRequest:
    """A decoded observation -> the ``/act`` request it stands for (the module doc's three steps, applied to the
    observation and to each frame of its ``chunk_frames``)."""
    obs = _renamed(message, image_fields, renames, "the observation")
    frames = obs.get("chunk_frames")
    if isinstance(frames, Mapping):
        obs["chunk_frames"] = {str(k.decode("utf-8", "replace") if isinstance(k, bytes) else k):
                               _renamed(f, image_fields, renames, f"chunk_frames[{k}]", strict=False)
                               if isinstance(f, Mapping) else f for k, f in frames.items()}
    try:
        req = protocol.request_from_payload(obs, image_fields)
    except protocol.ProtocolError as e:
        raise BadMessage(f"{e} (the observation's keys: {_keys(obs)}; rename with --ws-fields FROM=TO)") from None
    req.extra = {k: v for k, v in req.extra.items() if "/" not in k}  # a robot's own keys left unmapped: not sent on
    return req


def _keys(obs: Mapping) -> str:
    keys = sorted(map(str, obs))
    return ", ".join(keys[:20]) + (f" and {len(keys) - 20} more" if len(keys) > 20 else "")


def _short(x: Any, n: int = 300) -> str:
    """One line of at most ``n`` characters."""
    text = " ".join(str(x).split())
    return text if len(text) <= n else text[:n - 3] + "..."


ROBOARENA_ACTION_SPACES = {"pd_joint_pos": "joint_position", "pd_joint_vel": "joint_velocity"}  # ManiSkill's names


def roboarena_config(cameras: tuple[str, ...], task: Any) -> dict[str, Any]:
    """RoboArena's ``PolicyServerConfig`` keys for a world model reading ``cameras`` of ``task`` (a TaskSpec): its
    exterior cameras (those whose name does not say wrist or hand) and whether one is a wrist camera; no stereo;
    the task's action space under RoboArena's name (``joint_position``, ``joint_velocity``), or, where it has none,
    what it is (RoboArena's evaluator then refuses to run it rather than run it as joint positions)."""
    wrist = [c for c in cameras if any(w in c.lower() for w in ("wrist", "hand", "gripper"))]
    space = ROBOARENA_ACTION_SPACES.get(task.control_mode)
    if space is None:
        space = (f"{task.control_mode} ({task.action_dim}-D, task {task.name}; not a RoboArena action space: "
                 f"{', '.join(ROBOARENA_ACTION_SPACES.values())})")
    return {"n_external_cameras": len(cameras) - len(wrist), "needs_wrist_camera": bool(wrist),
            "needs_stereo_camera": False, "action_space": space}


def metadata(proxy: Any) -> dict[str, Any]:
    """What ``proxy`` (a ``proxy.app.Proxy``) sends first on every connection: ``Proxy.summary`` (as ``GET /health``),
    the image fields it reads, and RoboArena's ``PolicyServerConfig`` keys: ``needs_session_id``,
    ``image_resolution`` (the upstream's view size where known) and :func:`roboarena_config`'s cameras and action
    space."""
    size = proxy.upstream.shape.image_size
    return {"server": "wamplan-proxy", **proxy.summary(), "image_fields": dict(proxy.request_map),
            "ws_fields": proxy.cfg.ws_fields, "needs_session_id": False,
            "image_resolution": None if size is None else [size, size],
            **roboarena_config(tuple(proxy.cameras), proxy.task)}


def ws_fields_warning(ws_fields: str, image_fields: tuple[str, ...]) -> str | None:
    """One line naming the ``--ws-fields`` targets that no part of the proxy reads (a typo, most often; they are
    forwarded to the upstream as extra fields, which only a WAM that reads them wants), or None."""
    known = {*image_fields, "proprio", "task_description", protocol.RETURN_ALL_FIELD, *PROXY_FIELDS, *ALIASES}
    odd = [dst for _, dst in parse_ws_fields(ws_fields) if dst not in known]
    if not odd:
        return None
    return (f"warning: --ws-fields maps to {odd}, which the proxy does not read and forwards to the upstream as is; "
            f"the fields it reads: {sorted(known - set(ALIASES))}")


def add_openpi_routes(app: FastAPI, proxy: Any, secret: str | None) -> None:
    """The WebSocket routes (``/`` and ``/s/<robot>``) and ``GET /healthz`` on ``app``, answered by ``proxy`` (a
    ``proxy.app.Proxy``: its ``respond``, ``restart``, ``sessions``)."""
    renames = parse_ws_fields(proxy.cfg.ws_fields)
    fields = tuple(proxy.request_map)
    connections = itertools.count(1)

    async def session(ws: WebSocket, robot: str) -> None:
        try:
            check_secret(ws, secret)  # type: ignore[arg-type]  # headers and query as a request's
        except Refused as r:
            await ws.send_denial_response(PlainTextResponse(r.message, status_code=r.status))
            return
        await ws.accept()
        conn = Connection(robot, f"{robot}/#ws-{next(connections)}")  # '#': no session_id can name it
        await ws.send_bytes(pack(metadata(proxy)))
        try:
            while True:
                msg = await ws.receive()
                if msg["type"] == "websocket.disconnect":
                    return
                t_in = time.perf_counter()
                if msg.get("bytes") is None:
                    await ws.send_text("wamplan proxy: send each observation as a binary msgpack frame, not text")
                    continue
                try:
                    reply = await run_in_threadpool(answer, msg["bytes"], conn, t_in)
                except (protocol.ProtocolError, UserError, UpstreamError) as e:
                    text = _short(e.message if isinstance(e, UpstreamError) else e)
                    log.warning("openpi %s: %s", conn.key, text)
                    await ws.send_text(f"wamplan proxy: {text}")
                    continue
                except Exception as e:
                    log.exception("openpi %s failed", conn.key)
                    await ws.send_text(f"wamplan proxy: the proxy failed on this message ({_short(reason(e))}); its "
                                       f"log has the traceback")
                    await ws.close(code=1011)
                    return
                await (ws.send_text(reply) if isinstance(reply, str) else ws.send_bytes(reply))
        except WebSocketDisconnect:
            pass
        finally:
            proxy.sessions.drop(conn.key)

    def answer(data: bytes, conn: "Connection", t_in: float) -> bytes | str:
        message = unpack(data)
        if not isinstance(message, Mapping):
            raise BadMessage(f"the message is a {type(message).__name__}, expected a dict (an observation)")
        message = dict(message)
        endpoint = message.pop("endpoint", "infer")
        if endpoint == "reset":
            sid = session_name(message.get("session_id"))
            named = sid is not None and sid in conn.named  # else the connection's own episode (RoboArena sends
            proxy.restart(f"{conn.robot}/{sid}" if named else conn.key, message.get("seed"))  # its id on reset only)
            return RESET_REPLY
        if endpoint != "infer":
            raise BadMessage(f"endpoint {_short(repr(endpoint), 60)} is not 'infer' or 'reset'")
        req = as_request(message, fields, renames)
        sid = session_name(req.extra.get("session_id"))  # respond() reads the same name from the request
        if sid is not None:
            conn.named.add(sid)
        resp = proxy.respond(req, conn.robot, key=conn.key, t_in=t_in)
        out = protocol.response_payload(resp)
        out["server_timing"] = {"infer_ms": 1000.0 * (time.perf_counter() - t_in)}
        return pack(out)

    @app.websocket(WS_ROUTE)
    async def ws_default(ws: WebSocket) -> None:
        await session(ws, DEFAULT_ROBOT)

    @app.websocket(WS_SESSION_ROUTE)
    async def ws_robot(ws: WebSocket, robot: str) -> None:
        await session(ws, robot)

    @app.get(HEALTHZ_ROUTE)
    async def healthz() -> PlainTextResponse:
        state = proxy.health.read()  # as GET /health: 503 with the reason while the upstream does not answer
        if state["ok"]:
            return PlainTextResponse("OK\n")
        return PlainTextResponse(f"upstream down: {state['reason']}\n", status_code=503)


class Connection:
    """One WebSocket connection: its robot, its own session's key, the session_ids its messages have named."""

    def __init__(self, robot: str, key: str):
        self.robot, self.key = robot, key
        self.named: set[str] = set()
