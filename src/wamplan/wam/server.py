"""Serve any WAM over the Cosmos Policy ``/act`` protocol (``wamplan wam serve``).

The server speaks Cosmos Policy's ``deploy.py`` protocol: ``POST /act`` with json_numpy bodies, so
:class:`~wamplan.wam.cosmos_client.CosmosPolicyClient` and upstream's own robot client (``run_aloha_eval.py``,
``get_action_from_server``) both parse every answer:

* a proprio of another length than the model's (ALOHA's 14-D qpos) is refused (HTTP 400, one line), unless the
  server runs with ``fit_proprio`` (``--fit-proprio``): then it is padded with zeros or truncated to the model's size,
  and the answer's ``wamplan`` field says so;
* the value goes out as ``value_prediction`` and ``value_predictions`` (``VALUE_STANDIN`` where the model has
  none, said in the ``wamplan`` field); ``return_all_query_results`` adds upstream's ``all_*`` lists;
* an ``{"encoded": ...}`` request is answered double-encoded, as upstream answers it;
* actions the WAM returns outside [-1, 1] are clipped, and the answer's ``wamplan`` field and the server's log
  say how many entries changed (once per answer).

Errors come in two modes (``wamplan.serving.ERROR_MODES``):

* ``"http"`` (default, for wamplan's client): a malformed request (bad JSON, a missing field, an image of the
  wrong shape or dtype, non-finite proprio) is HTTP 400, a request the WAM refuses HTTP 422, a failure of the
  WAM itself HTTP 500, each with a one-line ``{"error": "..."}`` (the wamplan client prints it);
* ``"upstream"`` (the one to use with upstream clients): every failure is answered as Cosmos Policy's server
  answers it, HTTP 200 with the JSON string ``"error"``; the server's log has the reason and says what it answered.

For real use it adds what :mod:`wamplan.serving` provides both servers: it listens on 127.0.0.1 unless told
otherwise; an optional shared secret (with one, ``/act`` needs it in the ``X-WAMplan-Secret`` header, as
``Authorization: Bearer <secret>``, or in the URL as ``?token=<secret>``; without it, HTTP 401 with a one-line JSON
error, ``"error"`` in the upstream mode); a request size limit (HTTP 413 before the body is read); and
``GET /health`` (no secret needed): ``{"ok": true, "wam": ..., "task": ..., "chunk_length": ..., "action_dim": ...,
"cameras": [...], "image_size": ...}`` (``image_size`` None where the WAM does not say).

    app = create_app(wam, secret="s3cret")     # a FastAPI app
    serve(wam, host="127.0.0.1", port=8777)    # blocking, uvicorn
    with BackgroundServer(create_app(wam)) as srv:   # wamplan.serving.runner: in-process, on a free loopback port
        client = CosmosPolicyClient(url=srv.url + protocol.ROUTE)
"""

from __future__ import annotations

import logging
import socket
import threading

import numpy as np
from fastapi import FastAPI, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response

from wamplan.envs.spec import Observation
from wamplan.errors import UserError, reason
from wamplan.serving import DEFAULT_HOST, DEFAULT_MAX_REQUEST_BYTES, HEALTH_ROUTE
from wamplan.serving.refusals import Refused, check_error_mode, check_secret, error_answer, read_body
from wamplan.serving.runner import run_app
from wamplan.wam import protocol
from wamplan.wam.base import WAM, WAMOutputError

log = logging.getLogger(__name__)


def create_app(wam: WAM, instruction_default: str | None = None, request_map: dict[str, str] | None = None,
               response_map: dict[str, str] | None = None, secret: str | None = None,
               max_request_bytes: int = DEFAULT_MAX_REQUEST_BYTES, bare_errors: bool = False,
               errors: str = "http", fit_proprio: bool = False) -> FastAPI:
    """A FastAPI app answering ``POST /act`` with ``wam``'s predictions, and ``GET /health``.

    ``instruction_default`` (default: the WAM's ``default_instruction``) is used when a request's
    ``task_description`` is empty; ``request_map`` / ``response_map`` default to :func:`protocol.default_maps`
    of the WAM's cameras. ``secret`` (None or empty: none) must come with every ``/act`` request;
    bodies over ``max_request_bytes`` are refused (413). Queries are serialised (one at a time), since a WAM
    may keep state and hold a single model. ``errors``: the error mode (``wamplan.serving.ERROR_MODES``, module
    docstring); ``bare_errors`` is the same as ``errors="upstream"``. A proprio of another length than the
    model's is refused (400) unless ``fit_proprio`` (then padded with zeros or truncated, said in the answer).
    """
    if max_request_bytes < 1:
        raise UserError(f"the request size limit must be >= 1 byte, got {max_request_bytes}")
    errors = "upstream" if bare_errors else check_error_mode(errors)
    secret = secret or None
    try:
        request_map, response_map = protocol.resolve_maps(tuple(wam.cameras), request_map, response_map)
    except UserError as e:
        raise UserError(f"WAM '{wam.name}': {e}") from e
    if instruction_default is None:
        instruction_default = wam.default_instruction
    proprio_dim = int(wam.task.proprio_dim)
    image_size = getattr(getattr(wam, "config", None), "image_size", None)  # its predicted views' side, if it says
    lock = threading.Lock()
    app = FastAPI(title=f"wamplan WAM server ({wam.name})")
    app.state.field_map = protocol.field_map(request_map, response_map)

    def handle(body: bytes) -> str:
        req = protocol.decode_request(body, tuple(request_map))
        notes = []
        proprio, note = protocol.fit_proprio(req.proprio, proprio_dim, fit_proprio)  # (P,)
        notes += [note] if note else []
        images = {cam: req.images[name] for name, cam in request_map.items()}  # camera -> (H, W, 3)
        # The protocol carries no control step; a WAM must not depend on obs.step.
        obs = Observation(step=0, proprio=proprio, images=images)
        instruction = req.task_description or instruction_default
        with lock:
            out = wam.predict(obs, instruction)
        if isinstance(getattr(out, "actions", None), np.ndarray) and out.actions.dtype == np.float32 \
                and np.isfinite(out.actions).all():
            out.actions, note = protocol.clip_actions(out.actions)  # (H, A)
            if note:
                log.warning("/act: %s", note)
                notes.append(note)
        out = wam.validate(out)
        future = {name: out.images[cam] for cam, name in response_map.items() if cam in out.images}
        resp = protocol.ActResponse(actions=out.actions, future_images=future, value=out.value,
                                    wamplan={"notes": notes} if notes else {})
        return protocol.encode_response(resp, all_query_results=req.return_all, double_encode=req.encoded)

    @app.get(HEALTH_ROUTE)
    async def health() -> dict:
        return {"ok": True, "wam": wam.name, "task": wam.task.name, "chunk_length": int(wam.chunk_length),
                "action_dim": int(wam.action_dim), "cameras": list(wam.cameras), "image_size": image_size}

    def failed(status: int, why: str) -> Response:
        return error_answer(errors, status, why, protocol.ROUTE)

    @app.post(protocol.ROUTE)
    async def act(request: Request) -> Response:
        try:
            check_secret(request, secret)
            body = await read_body(request, max_request_bytes)
        except Refused as r:
            return failed(r.status, r.message)
        try:
            content = await run_in_threadpool(handle, body)
        except protocol.ProtocolError as e:  # the request is malformed: the caller's to fix
            return failed(400, f"bad /act request: {e}")
        except WAMOutputError as e:  # the WAM broke its own contract
            return failed(500, str(e))
        except UserError as e:  # a well-formed request the WAM refuses
            return failed(422, f"the WAM '{wam.name}' cannot answer this request: {e}")
        except Exception as e:  # the WAM itself failed; the traceback is for the server's log
            log.exception("/act failed")
            return failed(500, f"the WAM '{wam.name}' failed on this request ({reason(e)}); the server's log has "
                               f"the traceback")
        return Response(content=content, media_type="application/json")

    return app


def serve(wam: WAM, host: str = DEFAULT_HOST, port: int = protocol.DEFAULT_PORT,
          instruction_default: str | None = None, log_level: str = "info", secret: str | None = None,
          max_request_bytes: int = DEFAULT_MAX_REQUEST_BYTES, bare_errors: bool = False,
          errors: str = "http", sock: socket.socket | None = None, fit_proprio: bool = False) -> None:
    """Serve ``wam`` until interrupted (blocking), on ``sock`` (from :func:`wamplan.serving.runner.bind_socket`) or
    a socket bound to ``host:port`` here."""
    app = create_app(wam, instruction_default, secret=secret, max_request_bytes=max_request_bytes,
                     bare_errors=bare_errors, errors=errors, fit_proprio=fit_proprio)
    run_app(app, host, port, secret, log_level, sock)
