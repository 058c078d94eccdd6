"""The planning proxy's second front end: openpi's WebSocket protocol (and RoboArena's additions to it).

An unmodified openpi robot client (``openpi_client.websocket_client_policy.WebsocketClientPolicy``) connects to
``ws://HOST:PORT`` (or ``ws://HOST:PORT/s/<robot>``), reads the proxy's metadata (a msgpack dict, sent first), and
then sends one msgpack observation per chunk boundary and reads one msgpack answer: ``actions`` (H, A) float32, the
upstream's other fields, a ``wamplan`` field (as on ``/act``) and openpi's ``server_timing``. Arrays travel in
openpi's msgpack form ``{"__ndarray__": True, "data": bytes, "dtype": str, "shape": [...]}``.

* **One session per connection**: a connection starts an episode and its session is dropped when it closes. A
  message's ``session_id`` (RoboArena) names a session instead (``<robot>/<session_id>``, kept until idle).
* **RoboArena's** ``endpoint``: ``"infer"`` (the default) or ``"reset"``, which starts a new episode (with the
  message's ``seed``, if any) and is answered with the text ``reset successful``.
* **An observation** is read as an ``/act`` request (the same fields, the same proxy fields: ``reset``, ``seed``,
  ``chunk_frames``, ``executed_actions``) after three steps: nested dicts are flattened with ``/`` (openpi's ALOHA
  ``images`` -> ``images/cam_high``); ``--ws-fields`` renames keys (``FROM=TO``; ``A+B=proprio`` joins several
  vectors); openpi's ``prompt`` and ``state`` stand for ``task_description`` and ``proprio`` where those are
  absent. Images may come channels-first (3, H, W), as openpi's ALOHA client sends them.
* **Errors** are a text frame with one line (openpi's client raises it as ``RuntimeError``): the connection stays
  open after a bad message or an upstream failure, and is closed (1011) only after a failure of the proxy itself.
  A missing or wrong secret refuses the connection (HTTP 401); openpi's client sends it as
  ``Authorization: Api-Key SECRET`` (its ``api_key``).
"""

from __future__ import annotations

import itertools
import logging
import time
from typing import TYPE_CHECKING, Any, Mapping

import msgpack
import numpy as np
from fastapi import FastAPI, WebSocket, WebSocketDisconnect
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import PlainTextResponse

from wamplan.errors import UserError, reason
from wamplan.proxy.config import DEFAULT_ROBOT, PROXY_FIELDS
from wamplan.proxy.upstream import UpstreamError
from wamplan.wam import protocol
from wamplan.wam.server import Refused, check_secret

if TYPE_CHECKING:
    from wamplan.proxy.app import Proxy

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
    """msgpack's object hook: openpi's array dicts (bytes or text keys) -> numpy arrays (writable copies)."""
    d = {k.decode() if isinstance(k, bytes) else k: v for k, v in obj.items()}
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
def parse_ws_fields(spec: str) -> list[tuple[tuple[str, ...], str]]:
    """``"A=x,B+C=proprio"`` -> [(("A",), "x"), (("B", "C"), "proprio")]; UserError on a malformed entry."""
    out = []
    for item in filter(None, (p.strip() for p in spec.split(","))):
        src, eq, dst = item.partition("=")
        sources = tuple(s.strip() for s in src.split("+"))
        if not eq or not dst.strip() or not all(sources):
            raise UserError(f"--ws-fields entry {item!r} is not FROM=TO (e.g. observation/state=proprio, or "
                            f"observation/joint_position+observation/gripper_position=proprio)")
        out.append((sources, dst.strip()))
    return out


def _flat(d: Mapping, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        name = f"{prefix}{k.decode() if isinstance(k, bytes) else k}"
        if isinstance(v, Mapping) and name not in PROXY_FIELDS:  # chunk_frames keeps its nesting
            out.update(_flat(v, name + "/"))
        else:
            out[name] = v
    return out


def _channels_last(x: Any) -> Any:
    if isinstance(x, np.ndarray) and x.ndim in (3, 4) and x.shape[-3] == 3 and x.shape[-1] != 3:
        return np.moveaxis(x, -3, -1)  # (3, H, W) -> (H, W, 3)
    return x


def _renamed(message: Mapping, image_fields: tuple[str, ...], renames: list[tuple[tuple[str, ...], str]],
             what: str) -> dict[str, Any]:
    """One observation (or one frame of ``chunk_frames``) flattened, renamed, aliased, its images channels-last."""
    obs = _flat(message)
    for sources, dst in renames:
        missing = [s for s in sources if s not in obs]
        if missing:
            raise BadMessage(f"{what} lacks {missing}, which --ws-fields maps to {dst!r} (it has {sorted(obs)})")
        if len(sources) == 1:
            obs[dst] = obs.pop(sources[0])
        else:
            parts = [np.atleast_1d(np.asarray(obs.pop(s), dtype=np.float32)).reshape(-1) for s in sources]
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
        obs["chunk_frames"] = {str(k.decode() if isinstance(k, bytes) else k):
                               _renamed(f, image_fields, renames, f"chunk_frames[{k}]") if isinstance(f, Mapping) else f
                               for k, f in frames.items()}
    sid = obs.get("session_id")
    if isinstance(sid, np.ndarray) and sid.size == 1:  # RoboArena may send it as a (1,) array
        obs["session_id"] = sid.reshape(-1)[0].item()
    try:
        return protocol.request_from_payload(obs, image_fields)
    except protocol.ProtocolError as e:
        raise BadMessage(f"{e} (the observation's keys: {sorted(obs)}; rename with --ws-fields FROM=TO)") from None


def metadata(proxy: "Proxy") -> dict[str, Any]:
    """What the proxy sends first on every connection (openpi's metadata; RoboArena's ``needs_session_id``)."""
    return {"server": "wamplan-proxy", "upstream": proxy.upstream.where, "task": proxy.task.name,
            "chunk_length": proxy.chunk, "action_dim": proxy.upstream.shape.action_dim or len(proxy.columns),
            "image_fields": dict(proxy.request_map), "ws_fields": proxy.cfg.ws_fields,
            "world_model": proxy.cfg.world_model, "needs_session_id": False, "image_resolution": None}


def add_openpi_routes(app: FastAPI, proxy: "Proxy", secret: str | None) -> None:
    """The WebSocket routes (``/`` and ``/s/<robot>``) and ``GET /healthz`` on the proxy's ``app``."""
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
        key = f"{robot}/ws-{next(connections)}"
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
                    reply = await run_in_threadpool(answer, msg["bytes"], robot, key, t_in)
                except (protocol.ProtocolError, UserError, UpstreamError) as e:
                    text = e.message if isinstance(e, UpstreamError) else str(e)
                    log.warning("openpi %s: %s", key, text)
                    await ws.send_text(f"wamplan proxy: {text}")
                    continue
                except Exception as e:
                    log.exception("openpi %s failed", key)
                    await ws.send_text(f"wamplan proxy: the proxy failed on this message ({reason(e)}); its log has "
                                       f"the traceback")
                    await ws.close(code=1011)
                    return
                await (ws.send_text(reply) if isinstance(reply, str) else ws.send_bytes(reply))
        except WebSocketDisconnect:
            pass
        finally:
            proxy.sessions.drop(key)

    def answer(data: bytes, robot: str, key: str, t_in: float) -> bytes | str:
        message = unpack(data)
        if not isinstance(message, Mapping):
            raise BadMessage(f"the message is a {type(message).__name__}, expected a dict (an observation)")
        message = dict(message)
        endpoint = message.pop("endpoint", "infer")
        if endpoint == "reset":
            sid = message.get("session_id")
            proxy.restart(key if sid is None else f"{robot}/{sid}", message.get("seed"))
            return RESET_REPLY
        if endpoint != "infer":
            raise BadMessage(f"endpoint {endpoint!r} is not 'infer' or 'reset'")
        resp = proxy.respond(as_request(message, fields, renames), robot, key=key, t_in=t_in)
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
        return PlainTextResponse("OK\n")
