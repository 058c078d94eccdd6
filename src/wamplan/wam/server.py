"""Serve any WAM over the Cosmos Policy ``/act`` protocol (``wamplan wam serve``).

The server speaks Cosmos Policy's ``deploy.py`` protocol: ``POST /act`` with json_numpy bodies, so
:class:`~wamplan.wam.cosmos_client.CosmosPolicyClient` talks to either one unchanged. Where it fails it says why:
a malformed request (bad JSON, a missing field, an image of the wrong shape or dtype, non-finite proprio) is
answered HTTP 400, a request the WAM refuses (e.g. a proprio of the wrong length) HTTP 422, and a failure of the
WAM itself HTTP 500, each with a one-line ``{"error": "..."}`` (the wamplan client prints it). Cosmos Policy's
own server answers every failure with HTTP 200 and the bare JSON string ``"error"``; a client written for that
(one that checks for ``"error"`` and reads any other answer as a prediction) gets exactly that with
``bare_errors=True`` (``wamplan wam serve --bare-errors``). For real use it adds:

* it listens on 127.0.0.1 unless told otherwise;
* an optional shared secret: with one, ``/act`` needs it in the ``X-WAMplan-Secret`` header (or
  ``Authorization: Bearer <secret>``) and answers HTTP 401 with a one-line JSON error without it;
* a request size limit: a larger body is refused with HTTP 413 before it is read;
* ``GET /health`` (no secret needed): ``{"ok": true, "wam": ..., "task": ..., "chunk_length": ..., "cameras": [...]}``.

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

class _Refused(Exception):
    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status, self.message = status, message


def _presented_secret(request: Request) -> str | None:
    given = request.headers.get(protocol.SECRET_HEADER)
    if given is None:
        scheme, _, token = request.headers.get("authorization", "").partition(" ")
        given = token.strip() if scheme.lower() == "bearer" else None
    return given


async def _read_body(request: Request, limit: int) -> bytes:
    """The request body, or _Refused(413) as soon as it is known to pass ``limit`` bytes."""
    too_big = f"request body over the server's limit of {limit} bytes; send smaller images (the client's " \
              f"send_image_size; wamplan's --wam-profile presets send 224 px) or restart the server with a larger " \
              f"--max-request-mb"
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise _Refused(413, too_big.replace("request body", f"request body of {int(declared)} bytes", 1))
    body = bytearray()
    async for chunk in request.stream():  # also bounds bodies sent without a Content-Length
        body += chunk
        if len(body) > limit:
            raise _Refused(413, too_big)
    return bytes(body)


def create_app(wam: WAM, instruction_default: str | None = None, request_map: dict[str, str] | None = None,
               response_map: dict[str, str] | None = None, secret: str | None = None,
               max_request_bytes: int = protocol.DEFAULT_MAX_REQUEST_BYTES, bare_errors: bool = False) -> FastAPI:
    """A FastAPI app answering ``POST /act`` with ``wam``'s predictions, and ``GET /health``.

    ``instruction_default`` (default: the WAM's ``default_instruction``) is used when a request's
    ``task_description`` is empty; ``request_map`` / ``response_map`` default to :func:`protocol.default_maps`
    of the WAM's cameras. ``secret`` (None or empty: none) must come with every ``/act`` request;
    bodies over ``max_request_bytes`` are refused (413). Queries are serialised (one at a time), since a WAM
    may keep state and hold a single model. A request that fails is answered 400 / 422 / 500 with
    ``{"error": reason}`` (module docstring), or, with ``bare_errors``, as Cosmos Policy does: HTTP 200, ``"error"``.
    """
    if max_request_bytes < 1:
        raise UserError(f"the request size limit must be >= 1 byte, got {max_request_bytes}")
    secret = secret or None
    default_request, default_response = protocol.default_maps(tuple(wam.cameras))
    request_map = dict(request_map or default_request)
    response_map = dict(response_map or default_response)
    bad = sorted(set(request_map) - {f for fs in protocol.REQUEST_IMAGE_FIELD_SETS for f in fs})
    bad += sorted(set(response_map.values()) - set(protocol.KNOWN_RESPONSE_IMAGE_FIELDS))
    if bad:
        raise UserError(f"unknown /act field(s) {bad}; request fields are {list(protocol.REQUEST_IMAGE_FIELD_SETS)}, "
                        f"response fields {list(protocol.KNOWN_RESPONSE_IMAGE_FIELDS)}")
    unfed = [c for c in wam.cameras if c not in request_map.values()]
    if unfed:
        raise UserError(f"WAM '{wam.name}' reads camera(s) {unfed} that no request field carries "
                        f"(request map: {request_map}); map them to a request field")
    if instruction_default is None:
        instruction_default = wam.default_instruction
    lock = threading.Lock()
    app = FastAPI(title=f"wamplan WAM server ({wam.name})")

    def handle(body: bytes) -> str:
        req = protocol.decode_request(body, tuple(request_map))
        images = {cam: req.images[name] for name, cam in request_map.items()}  # camera -> (H, W, 3)
        # The protocol carries no control step; a WAM must not depend on obs.step.
        obs = Observation(step=0, proprio=req.proprio, images=images)
        instruction = req.task_description or instruction_default
        with lock:
            out = wam.validate(wam.predict(obs, instruction))
        future = {name: out.images[cam] for cam, name in response_map.items() if cam in out.images}
        return protocol.encode_response(protocol.ActResponse(actions=out.actions, future_images=future,
                                                             value=out.value))

    @app.get(protocol.HEALTH_ROUTE)
    async def health() -> dict:
        return {"ok": True, "wam": wam.name, "task": wam.task.name, "chunk_length": int(wam.chunk_length),
                "cameras": list(wam.cameras)}

    @app.post(protocol.ROUTE)
    async def act(request: Request) -> Response:
        try:
            if secret is not None:
                given = _presented_secret(request)
                if given is None or not hmac.compare_digest(given.encode(), secret.encode()):
                    raise _Refused(401, f"missing or wrong shared secret: send it in the {protocol.SECRET_HEADER} "
                                        f"header (the wamplan client reads ${protocol.SECRET_ENV})")
            body = await _read_body(request, max_request_bytes)
        except _Refused as r:
            log.warning("/act refused (HTTP %d): %s", r.status, r.message)
            return JSONResponse({"error": r.message}, status_code=r.status)
        try:
            content = await run_in_threadpool(handle, body)
        except protocol.ProtocolError as e:  # the request is malformed: the caller's to fix
            return failed(400, f"bad /act request: {e}")
        except WAMOutputError as e:  # the WAM broke its own contract
            log.warning("/act failed: %s", e)
            return failed(500, str(e))
        except UserError as e:  # a well-formed request the WAM refuses (e.g. its proprio length)
            return failed(422, f"the WAM '{wam.name}' cannot answer this request: {e}")
        except Exception as e:  # the WAM itself failed; the traceback is for the server's log
            log.exception("/act failed")
            return failed(500, f"the WAM '{wam.name}' failed on this request ({reason(e)}); the server's log has "
                               f"the traceback")
        return Response(content=content, media_type="application/json")

    def failed(status: int, reason: str) -> Response:
        if status < 500:
            log.warning("/act refused (HTTP %d): %s", status, reason)
        if bare_errors:  # Cosmos Policy's answer to any failure
            return Response(content=protocol.error_reply(), media_type="application/json")
        return JSONResponse({"error": reason}, status_code=status)

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
          sock: socket.socket | None = None) -> None:
    """Serve ``wam`` until interrupted (blocking), on ``sock`` (from :func:`bind_socket`) or a socket bound to
    ``host:port`` here."""
    app = create_app(wam, instruction_default, secret=secret, max_request_bytes=max_request_bytes,
                     bare_errors=bare_errors)
    if not is_loopback(host) and not secret:
        log.warning("listening on %s without a shared secret: anyone who reaches this port can query the WAM; "
                    "set $%s (or --secret)", host, protocol.SECRET_ENV)
    sock = sock or bind_socket(host, port)
    config = uvicorn.Config(app, log_level=log_level)
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

