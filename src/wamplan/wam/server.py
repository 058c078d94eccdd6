"""Serve any WAM over the Cosmos Policy ``/act`` protocol (``wamplan wam serve``).

The server speaks Cosmos Policy's ``deploy.py`` protocol: ``POST /act`` with json_numpy bodies, so
:class:`~wamplan.wam.cosmos_client.CosmosPolicyClient` and upstream's own robot client (``run_aloha_eval.py``,
``get_action_from_server``) both parse every answer:

* a proprio of another length than the model's (ALOHA's 14-D qpos) is padded with zeros or truncated to the
  model's size, and the answer's ``wamplan`` field says so;
* the value goes out as ``value_prediction`` and ``value_predictions`` (``VALUE_STANDIN`` where the model has
  none, said in the ``wamplan`` field); ``return_all_query_results`` adds upstream's ``all_*`` lists;
* an ``{"encoded": ...}`` request is answered double-encoded, as upstream answers it;
* actions the WAM returns outside [-1, 1] are clipped, and the answer's ``wamplan`` field and the server's log
  say how many entries changed (once per answer).

Errors come in two modes (``ERROR_MODES``):

* ``"http"`` (default, for wamplan's client): a malformed request (bad JSON, a missing field, an image of the
  wrong shape or dtype, non-finite proprio) is HTTP 400, a request the WAM refuses HTTP 422, a failure of the
  WAM itself HTTP 500, each with a one-line ``{"error": "..."}`` (the wamplan client prints it);
* ``"upstream"`` (the one to use with upstream clients): every failure is answered as Cosmos Policy's server
  answers it, HTTP 200 with the JSON string ``"error"``; the server's log has the reason and says what it answered.

For real use it adds:

* it listens on 127.0.0.1 unless told otherwise;
* an optional shared secret: with one, ``/act`` needs it in the ``X-WAMplan-Secret`` header, as
  ``Authorization: Bearer <secret>``, or in the URL as ``?token=<secret>`` (for a client that cannot send
  headers: put it in the client's server URL); without it, HTTP 401 with a one-line JSON error (``"error"`` in
  the upstream mode);
* a request size limit: a larger body is refused with HTTP 413 before it is read;
* ``GET /health`` (no secret needed): ``{"ok": true, "wam": ..., "task": ..., "chunk_length": ..., "action_dim": ...,
  "cameras": [...], "image_size": ...}`` (``image_size`` None where the WAM does not say).

    app = create_app(wam, secret="s3cret")     # a FastAPI app
    serve(wam, host="127.0.0.1", port=8777)    # blocking, uvicorn
    with BackgroundServer(create_app(wam)) as srv:   # in-process, on a free loopback port
        client = CosmosPolicyClient(url=srv.act_url)
"""

from __future__ import annotations

import hmac
import ipaddress
import logging
import socket
import threading
import time

import numpy as np
import uvicorn
from fastapi import FastAPI, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, Response

from wamplan.envs.spec import Observation
from wamplan.errors import UserError, reason
from wamplan.wam import protocol
from wamplan.wam.base import WAM, WAMOutputError

log = logging.getLogger(__name__)

DEFAULT_HOST = "127.0.0.1"  # loopback: other machines reach the server only when --host says so
ERROR_MODES = ("http", "upstream")  # how failures are answered (module docstring)


class Refused(Exception):
    """A request answered with HTTP ``status`` (in the "http" error mode) and the one-line ``message``."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status, self.message = status, message


def presented_secret(request: Request) -> str | None:
    """The secret a request (or WebSocket) carries: the header, ``Authorization: Bearer`` or ``Api-Key`` (openpi's
    client), or the ``?token=`` query parameter."""
    given = request.headers.get(protocol.SECRET_HEADER)
    if given is None:
        scheme, _, token = request.headers.get("authorization", "").partition(" ")
        given = token.strip() if scheme.lower() in ("bearer", "api-key") else None  # api-key: openpi's client
    if given is None:
        given = request.query_params.get(protocol.SECRET_QUERY)
    return given


def check_secret(request: Request, secret: str | None) -> None:
    """Raise Refused(401) unless ``secret`` is None or the request carries it."""
    if secret is None:
        return
    given = presented_secret(request)
    if given is None or not hmac.compare_digest(given.encode(), secret.encode()):
        raise Refused(401, f"missing or wrong shared secret: send it in the {protocol.SECRET_HEADER} header, as "
                           f"Authorization: Bearer or Api-Key (openpi's api_key), or as ?{protocol.SECRET_QUERY}=SECRET "
                           f"in the URL (the wamplan client reads ${protocol.SECRET_ENV})")


async def read_body(request: Request, limit: int) -> bytes:
    """The request body, or Refused(413) as soon as it is known to pass ``limit`` bytes."""
    too_big = f"request body over the server's limit of {limit} bytes; send smaller images (the client's " \
              f"send_image_size; wamplan's --wam-profile presets send 224 px) or restart the server with a larger " \
              f"--max-request-mb"
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise Refused(413, too_big.replace("request body", f"request body of {int(declared)} bytes", 1))
    body = bytearray()
    async for chunk in request.stream():  # also bounds bodies sent without a Content-Length
        body += chunk
        if len(body) > limit:
            raise Refused(413, too_big)
    return bytes(body)


def check_error_mode(errors: str) -> str:
    if errors not in ERROR_MODES:
        raise UserError(f"unknown error mode '{errors}'; choose one of {list(ERROR_MODES)} (upstream: for Cosmos "
                        f"Policy's own clients)")
    return errors


def error_answer(errors: str, status: int, why: str, route: str = protocol.ROUTE) -> Response:
    """The answer to a failed request in error mode ``errors``, logged as what is answered."""
    if errors == "upstream":  # Cosmos Policy's answer to any failure
        log.warning('%s failed, answered HTTP 200 "error" (upstream error mode): %s', route, why)
        return Response(content=protocol.error_reply(), media_type="application/json")
    if status < 500:
        log.warning("%s refused (HTTP %d): %s", route, status, why)
    else:
        log.warning("%s failed (HTTP %d): %s", route, status, why)
    return JSONResponse({"error": why}, status_code=status)


def fit_proprio(proprio: np.ndarray, size: int) -> tuple[np.ndarray, str | None]:
    """(P,) -> (size,) float32: zero-padded or truncated to the model's size, with the note that says so
    (None when it already fits)."""
    n = proprio.shape[0]
    if n == size:
        return proprio, None
    out = np.zeros(size, dtype=np.float32)  # (size,)
    out[:min(n, size)] = proprio[:min(n, size)]
    how = f"truncated to its first {size}" if n > size else f"padded with zeros to {size}"
    return out, f"proprio of {n} entries {how}, the model's size"


def clip_actions(actions: np.ndarray) -> tuple[np.ndarray, str | None]:
    """(H, A) -> (H, A) clipped to [-1, 1], with the note saying how many entries changed (None if none did)."""
    clipped = np.clip(actions, -1.0, 1.0).astype(np.float32)  # (H, A)
    changed = int(np.count_nonzero(clipped != actions))
    if not changed:
        return clipped, None
    return clipped, (f"{changed} of {actions.size} action entries were outside [-1, 1] (max |a| = "
                     f"{float(np.abs(actions).max()):.4g}) and were clipped")


def field_map(request_map: dict[str, str], response_map: dict[str, str]) -> str:
    """One line: which request field feeds each camera and which answer field carries its prediction."""
    req = ", ".join(f"{name} -> {cam}" for name, cam in request_map.items())
    resp = ", ".join(f"{cam} -> {name}" for cam, name in response_map.items())
    return f"request fields: {req}; predictions: {resp}"


def resolve_maps(cameras: tuple[str, ...], request_map: dict[str, str] | None = None,
                 response_map: dict[str, str] | None = None) -> tuple[dict[str, str], dict[str, str]]:
    """The maps a server for ``cameras`` uses (``protocol.default_maps`` where none are given), checked."""
    default_request, default_response = protocol.default_maps(tuple(cameras))
    request_map = dict(request_map or default_request)
    response_map = dict(response_map or default_response)
    bad = sorted(set(request_map) - {f for fs in protocol.REQUEST_IMAGE_FIELD_SETS for f in fs})
    bad += sorted(set(response_map.values()) - set(protocol.KNOWN_RESPONSE_IMAGE_FIELDS))
    if bad:
        raise UserError(f"unknown /act field(s) {bad}; request fields are {list(protocol.REQUEST_IMAGE_FIELD_SETS)}, "
                        f"response fields {list(protocol.KNOWN_RESPONSE_IMAGE_FIELDS)}")
    unfed = [c for c in cameras if c not in request_map.values()]
    if unfed:
        raise UserError(f"camera(s) {unfed} are carried by no request field (request map: {request_map}); map them "
                        f"to a request field")
    return request_map, response_map


def create_app(wam: WAM, instruction_default: str | None = None, request_map: dict[str, str] | None = None,
               response_map: dict[str, str] | None = None, secret: str | None = None,
               max_request_bytes: int = protocol.DEFAULT_MAX_REQUEST_BYTES, bare_errors: bool = False,
               errors: str = "http") -> FastAPI:
    """A FastAPI app answering ``POST /act`` with ``wam``'s predictions, and ``GET /health``.

    ``instruction_default`` (default: the WAM's ``default_instruction``) is used when a request's
    ``task_description`` is empty; ``request_map`` / ``response_map`` default to :func:`protocol.default_maps`
    of the WAM's cameras. ``secret`` (None or empty: none) must come with every ``/act`` request;
    bodies over ``max_request_bytes`` are refused (413). Queries are serialised (one at a time), since a WAM
    may keep state and hold a single model. ``errors``: the error mode (``ERROR_MODES``, module docstring);
    ``bare_errors`` is the same as ``errors="upstream"``.
    """
    if max_request_bytes < 1:
        raise UserError(f"the request size limit must be >= 1 byte, got {max_request_bytes}")
    errors = "upstream" if bare_errors else check_error_mode(errors)
    secret = secret or None
    try:
        request_map, response_map = resolve_maps(tuple(wam.cameras), request_map, response_map)
    except UserError as e:
        raise UserError(f"WAM '{wam.name}': {e}") from e
    if instruction_default is None:
        instruction_default = wam.default_instruction
    proprio_dim = int(wam.task.proprio_dim)
    image_size = getattr(getattr(wam, "config", None), "image_size", None)  # its predicted views' side, if it says
    lock = threading.Lock()
    app = FastAPI(title=f"wamplan WAM server ({wam.name})")
    app.state.field_map = field_map(request_map, response_map)

    def handle(body: bytes) -> str:
        req = protocol.decode_request(body, tuple(request_map))
        notes = []
        proprio, note = fit_proprio(req.proprio, proprio_dim)  # (P,)
        notes += [note] if note else []
        images = {cam: req.images[name] for name, cam in request_map.items()}  # camera -> (H, W, 3)
        # The protocol carries no control step; a WAM must not depend on obs.step.
        obs = Observation(step=0, proprio=proprio, images=images)
        instruction = req.task_description or instruction_default
        with lock:
            out = wam.predict(obs, instruction)
        if isinstance(getattr(out, "actions", None), np.ndarray) and out.actions.dtype == np.float32 \
                and np.isfinite(out.actions).all():
            out.actions, note = clip_actions(out.actions)  # (H, A)
            if note:
                log.warning("/act: %s", note)
                notes.append(note)
        out = wam.validate(out)
        future = {name: out.images[cam] for cam, name in response_map.items() if cam in out.images}
        resp = protocol.ActResponse(actions=out.actions, future_images=future, value=out.value,
                                    wamplan={"notes": notes} if notes else {})
        return protocol.encode_response(resp, all_query_results=req.return_all, double_encode=req.encoded)

    @app.get(protocol.HEALTH_ROUTE)
    async def health() -> dict:
        return {"ok": True, "wam": wam.name, "task": wam.task.name, "chunk_length": int(wam.chunk_length),
                "action_dim": int(wam.action_dim), "cameras": list(wam.cameras), "image_size": image_size}

    @app.post(protocol.ROUTE)
    async def act(request: Request) -> Response:
        try:
            check_secret(request, secret)
            body = await read_body(request, max_request_bytes)
        except Refused as r:
            return error_answer(errors, r.status, r.message)
        try:
            content = await run_in_threadpool(handle, body)
        except protocol.ProtocolError as e:  # the request is malformed: the caller's to fix
            return error_answer(errors, 400, f"bad /act request: {e}")
        except WAMOutputError as e:  # the WAM broke its own contract
            return error_answer(errors, 500, str(e))
        except UserError as e:  # a well-formed request the WAM refuses
            return error_answer(errors, 422, f"the WAM '{wam.name}' cannot answer this request: {e}")
        except Exception as e:  # the WAM itself failed; the traceback is for the server's log
            log.exception("/act failed")
            return error_answer(errors, 500, f"the WAM '{wam.name}' failed on this request ({reason(e)}); the "
                                             f"server's log has the traceback")
        return Response(content=content, media_type="application/json")

    return app


def bind_socket(host: str, port: int) -> socket.socket:
    """A listening-ready TCP socket on ``host:port`` (port 0: a free one), or a UserError saying why not."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as e:
        sock.close()
        raise UserError(f"cannot listen on {host}:{port} ({e.strerror or e}); pick another --port or --host, "
                        f"or stop the process using it") from e
    return sock


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def serve(wam: WAM, host: str = DEFAULT_HOST, port: int = protocol.DEFAULT_PORT,
          instruction_default: str | None = None, log_level: str = "info", secret: str | None = None,
          max_request_bytes: int = protocol.DEFAULT_MAX_REQUEST_BYTES, bare_errors: bool = False,
          errors: str = "http", sock: socket.socket | None = None) -> None:
    """Serve ``wam`` until interrupted (blocking), on ``sock`` (from :func:`bind_socket`) or a socket bound to
    ``host:port`` here."""
    app = create_app(wam, instruction_default, secret=secret, max_request_bytes=max_request_bytes,
                     bare_errors=bare_errors, errors=errors)
    run_app(app, host, port, secret, log_level, sock)


def run_app(app: FastAPI, host: str, port: int, secret: str | None, log_level: str = "info",
            sock: socket.socket | None = None, ws_max_bytes: int = protocol.DEFAULT_MAX_REQUEST_BYTES) -> None:
    """Serve ``app`` on ``sock`` or ``host:port`` until interrupted (blocking); warn when it is open to other
    machines. ``ws_max_bytes``: the largest WebSocket message taken."""
    if not is_loopback(host) and not secret:
        log.warning("listening on %s without a shared secret: anyone who reaches this port can query it; "
                    "set $%s (or --secret)", host, protocol.SECRET_ENV)
    sock = sock or bind_socket(host, port)
    config = uvicorn.Config(app, log_level=log_level, ws_max_size=ws_max_bytes)
    uvicorn.Server(config).run(sockets=[sock])


class BackgroundServer:
    """Run an app with uvicorn in a daemon thread on ``host:port`` (port 0: a free one); stop() ends it."""

    def __init__(self, app: FastAPI, host: str = DEFAULT_HOST, port: int = 0, log_level: str = "warning"):
        self.host = host
        self._sock = bind_socket(host, port)
        self.port = int(self._sock.getsockname()[1])
        self._server = uvicorn.Server(uvicorn.Config(app, log_level=log_level, timeout_graceful_shutdown=1))
        self._thread = threading.Thread(target=self._server.run, kwargs={"sockets": [self._sock]},
                                        name=f"wam-server-{self.port}", daemon=True)

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}"

    @property
    def act_url(self) -> str:
        return self.url + protocol.ROUTE

    @property
    def health_url(self) -> str:
        return self.url + protocol.HEALTH_ROUTE

    def start(self, timeout_s: float = 10.0) -> BackgroundServer:
        self._thread.start()
        deadline = time.monotonic() + timeout_s
        while not self._server.started:
            if not self._thread.is_alive() or time.monotonic() > deadline:
                raise RuntimeError(f"the WAM server on {self.url} did not start within {timeout_s:g} s")
            time.sleep(0.01)
        return self

    def stop(self, timeout_s: float = 10.0) -> None:
        self._server.should_exit = True
        if self._thread.is_alive():
            self._thread.join(timeout_s)
        self._sock.close()

    def __enter__(self) -> BackgroundServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

