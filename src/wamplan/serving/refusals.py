"""What a request must pass before a server reads it (the shared secret, the size limit), and how a failure is
answered in each error mode (:data:`wamplan.serving.ERROR_MODES`)."""

from __future__ import annotations

import hmac
import json
import logging

from fastapi import Request
from fastapi.responses import JSONResponse, Response

from wamplan.errors import UserError
from wamplan.serving import ERROR_MODES, ERROR_REPLY, SECRET_ENV, SECRET_HEADER, SECRET_QUERY

log = logging.getLogger(__name__)


class Refused(Exception):
    """A request answered with HTTP ``status`` (in the "http" error mode) and the one-line ``message``."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status, self.message = status, message


def presented_secret(request: Request) -> str | None:
    """The secret a request (or WebSocket) carries: the header, ``Authorization: Bearer`` or ``Api-Key`` (openpi's
    client), or the ``?token=`` query parameter."""
    given = request.headers.get(SECRET_HEADER)
    if given is None:
        scheme, _, token = request.headers.get("authorization", "").partition(" ")
        given = token.strip() if scheme.lower() in ("bearer", "api-key") else None  # api-key: openpi's client
    if given is None:
        given = request.query_params.get(SECRET_QUERY)
    return given


def check_secret(request: Request, secret: str | None) -> None:
    """Raise Refused(401) unless ``secret`` is None or the request carries it."""
    if secret is None:
        return
    given = presented_secret(request)
    if given is None or not hmac.compare_digest(given.encode(), secret.encode()):
        raise Refused(401, f"missing or wrong shared secret: send it in the {SECRET_HEADER} header, as "
                           f"Authorization: Bearer or Api-Key (openpi's api_key), or as ?{SECRET_QUERY}=SECRET "
                           f"in the URL (the wamplan client reads ${SECRET_ENV})")


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


def error_reply() -> str:
    """The body Cosmos Policy sends (with HTTP 200) when a request fails."""
    return json.dumps(ERROR_REPLY)


def error_answer(errors: str, status: int, why: str, route: str) -> Response:
    """The answer to a failed request to ``route`` in error mode ``errors``, logged as what is answered."""
    if errors == "upstream":  # Cosmos Policy's answer to any failure
        log.warning('%s failed, answered HTTP 200 "error" (upstream error mode): %s', route, why)
        return Response(content=error_reply(), media_type="application/json")
    if status < 500:
        log.warning("%s refused (HTTP %d): %s", route, status, why)
    else:
        log.warning("%s failed (HTTP %d): %s", route, status, why)
    return JSONResponse({"error": why}, status_code=status)
