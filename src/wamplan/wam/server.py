"""Serve any WAM over the Cosmos Policy ``/act`` protocol (``wamplan wam serve``).

The server behaves like Cosmos Policy's ``deploy.py``: ``POST /act`` only, json_numpy bodies, and on any
failure the JSON string ``"error"`` with HTTP 200 (the traceback goes to the server's log). So
:class:`~wamplan.wam.cosmos_client.CosmosPolicyClient` talks to either one unchanged.

    app = create_app(wam)                      # a FastAPI app
    serve(wam, host="127.0.0.1", port=8777)    # blocking, uvicorn
    with BackgroundServer(create_app(wam)) as srv:   # in-process, on a free loopback port
        client = CosmosPolicyClient(url=srv.act_url)
"""

from __future__ import annotations

import logging
import socket
import threading
import time

import uvicorn
from fastapi import FastAPI, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response

from wamplan.envs.contract import Observation
from wamplan.errors import UserError
from wamplan.wam import protocol
from wamplan.wam.base import WAM

log = logging.getLogger(__name__)

# request field -> wamplan camera, and wamplan camera -> response field (the client's defaults).
DEFAULT_REQUEST_MAP = {"primary_image": "front", "left_wrist_image": "side", "right_wrist_image": "wrist"}
DEFAULT_RESPONSE_MAP = {"front": "future_image", "side": "future_wrist_image", "wrist": "future_wrist_image2"}


def create_app(wam: WAM, instruction_default: str | None = None, request_map: dict[str, str] | None = None,
               response_map: dict[str, str] | None = None) -> FastAPI:
    """A FastAPI app answering ``POST /act`` with ``wam``'s predictions.

    ``instruction_default`` (default: the WAM's ``default_instruction``) is used when a request's
    ``task_description`` is empty. Queries are serialised
    (one at a time), since a WAM may keep state and hold a single model.
    """
    request_map = dict(request_map or DEFAULT_REQUEST_MAP)
    response_map = dict(response_map or DEFAULT_RESPONSE_MAP)
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

    @app.post(protocol.ROUTE)
    async def act(request: Request) -> Response:
        try:
            body = await request.body()
            content = await run_in_threadpool(handle, body)
        except Exception:  # any failure answers "error" (HTTP 200), exactly like Cosmos Policy
            log.exception("/act failed; answering \"error\"")
            content = protocol.error_reply()
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


def serve(wam: WAM, host: str = "127.0.0.1", port: int = protocol.DEFAULT_PORT,
          instruction_default: str | None = None, log_level: str = "info") -> None:
    """Serve ``wam`` until interrupted (blocking)."""
    sock = bind_socket(host, port)
    config = uvicorn.Config(create_app(wam, instruction_default), log_level=log_level)
    uvicorn.Server(config).run(sockets=[sock])


class BackgroundServer:
    """Run an app with uvicorn in a daemon thread on ``host:port`` (port 0: a free one); stop() ends it."""

    def __init__(self, app: FastAPI, host: str = "127.0.0.1", port: int = 0, log_level: str = "warning"):
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

