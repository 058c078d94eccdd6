"""The HTTP plumbing wamplan's two servers share, ``wamplan wam serve`` (:mod:`wamplan.wam.server`) and the planning
proxy (:mod:`wamplan.proxy`): what a real deployment adds around the ``/act`` protocol (:mod:`wamplan.wam.protocol`).

* an optional shared secret: in the ``SECRET_HEADER`` header, as ``Authorization: Bearer <secret>`` (or openpi's
  ``Api-Key``), or in the URL as ``?token=<secret>`` (``SECRET_QUERY``, for a client that cannot send headers);
  clients read it from ``SECRET_ENV``; without it a request is refused (HTTP 401);
* a request size limit (``DEFAULT_MAX_REQUEST_BYTES``): a larger body is refused with HTTP 413 before it is read;
* ``GET /health`` (``HEALTH_ROUTE``, no secret needed);
* two error modes (``ERROR_MODES``): ``"http"`` answers a failure with its status and a one-line
  ``{"error": "..."}``; ``"upstream"`` answers every failure as Cosmos Policy's server does, HTTP 200 with the JSON
  string ``ERROR_REPLY``, and the server's log has the reason;
* listening on loopback (``DEFAULT_HOST``) unless told otherwise.

This module holds only those names, so that clients read them without loading a web framework;
:mod:`wamplan.serving.refusals` checks requests and answers failures, :mod:`wamplan.serving.runner` runs an app.
"""

DEFAULT_HOST = "127.0.0.1"  # loopback: other machines reach a server only when --host says so
HEALTH_ROUTE = "/health"
SECRET_HEADER = "X-WAMplan-Secret"
SECRET_ENV = "WAMPLAN_ACT_SECRET"  # the shared secret, for `wamplan wam serve` and the client alike
SECRET_QUERY = "token"  # ...?token=SECRET: the secret in the URL, for clients that cannot send a header
DEFAULT_MAX_REQUEST_BYTES = 16 * 2**20  # three 224-px views in json_numpy take ~0.6 MB
ERROR_MODES = ("http", "upstream")  # how failures are answered (above)
ERROR_REPLY = "error"  # Cosmos Policy's answer to any failure (HTTP 200), and so the upstream error mode's
