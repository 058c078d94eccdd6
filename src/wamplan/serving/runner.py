"""Running a server's app: a listening socket, uvicorn until interrupted (:func:`run_app`), or uvicorn in a
background thread for tests and benchmarks (:class:`BackgroundServer`)."""

from __future__ import annotations

import ipaddress
import logging
import socket
import threading
import time

import uvicorn
from fastapi import FastAPI

from wamplan.errors import UserError
from wamplan.serving import DEFAULT_HOST, DEFAULT_MAX_REQUEST_BYTES, HEALTH_ROUTE, SECRET_ENV

log = logging.getLogger(__name__)


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


def run_app(app: FastAPI, host: str, port: int, secret: str | None, log_level: str = "info",
            sock: socket.socket | None = None, ws_max_bytes: int = DEFAULT_MAX_REQUEST_BYTES) -> None:
    """Serve ``app`` on ``sock`` or ``host:port`` until interrupted (blocking); warn when it is open to other
    machines. ``ws_max_bytes``: the largest WebSocket message taken."""
    if not is_loopback(host) and not secret:
        log.warning("listening on %s without a shared secret: anyone who reaches this port can query it; "
                    "set $%s (or --secret)", host, SECRET_ENV)
    sock = sock or bind_socket(host, port)
    config = uvicorn.Config(app, log_level=log_level, ws_max_size=ws_max_bytes)
    uvicorn.Server(config).run(sockets=[sock])


class BackgroundServer:
    """Run an app with uvicorn in a daemon thread on ``host:port`` (port 0: a free one); stop() ends it. A route's
    URL is ``url`` + the route (``/act``: ``wamplan.wam.protocol.ROUTE``)."""

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
    def health_url(self) -> str:
        return self.url + HEALTH_ROUTE

    def start(self, timeout_s: float = 10.0) -> BackgroundServer:
        self._thread.start()
        deadline = time.monotonic() + timeout_s
        while not self._server.started:
            if not self._thread.is_alive() or time.monotonic() > deadline:
                raise RuntimeError(f"the server on {self.url} did not start within {timeout_s:g} s")
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
