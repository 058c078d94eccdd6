"""What the planning proxy knows of its upstream's health, for ``GET /health`` and ``/healthz``
(:class:`UpstreamHealth`).

The state comes from the start-up probe (one rest observation sent to the upstream's ``/act``) and from every
``/act`` the proxy forwards; ``/health`` only reads it. When it is older than ``refresh_s`` a poll starts one
refresh in the background and answers what is known meanwhile, so a load balancer's polls never wait on the
upstream and never cost it an inference while it serves: an upstream last seen answering is checked with a request
that runs no model (``Upstream.alive``: a ``GET`` on its ``/act`` route); one last seen failing is probed again with
the rest observation (which costs an inference only once it answers again), and the proxy reports healthy as soon
as it does.
"""

from __future__ import annotations

import threading
import time
from typing import Any, Callable

from wamplan.proxy.upstream import Upstream, UpstreamError

DEFAULT_REFRESH_S = 5.0


class UpstreamHealth:
    """The upstream's last known state: ``ok`` (None: never checked), ``reason`` (one line), where it was learnt
    (``source``) and when. ``probe()`` asks the upstream the rest observation and checks its answer (raising
    UpstreamError)."""

    def __init__(self, upstream: Upstream, probe: Callable[[], None], refresh_s: float = DEFAULT_REFRESH_S):
        self.upstream, self.probe, self.refresh_s = upstream, probe, refresh_s
        self.ok: bool | None = None
        self.reason, self.source, self.at = "not checked yet", "start-up", time.monotonic()
        self._lock = threading.Lock()
        self._refreshing = False

    def record(self, ok: bool, reason: str, source: str) -> None:
        """What a probe, an ``/act`` or a check just learnt of the upstream."""
        with self._lock:
            self.ok, self.reason, self.source, self.at = ok, reason, source, time.monotonic()

    def failed(self, e: UpstreamError, source: str) -> None:
        self.record(False, e.message, source)

    def read(self) -> dict[str, Any]:
        """The state as ``/health`` reports it (``ok``, ``upstream_ok``, ``reason``, ``checked``, ``age_s``); a stale
        state starts one background refresh."""
        with self._lock:
            age = time.monotonic() - self.at
            if age >= self.refresh_s and not self._refreshing:
                self._refreshing = True
                threading.Thread(target=self._refresh, name="wamplan-upstream-health", daemon=True).start()
            return {"ok": bool(self.ok), "upstream_ok": self.ok, "reason": self.reason, "checked": self.source,
                    "age_s": round(age, 3)}

    def _refresh(self) -> None:
        try:
            if self.ok:
                why = self.upstream.alive()
                if why is None:
                    self.record(True, self.reason, self.source)  # still serving: the last answer's state holds
                else:
                    self.record(False, why, "health check")
            else:
                try:
                    self.probe()
                except UpstreamError as e:
                    self.failed(e, "health probe")
                else:
                    self.record(True, "it answered the rest observation", "health probe")
        finally:
            with self._lock:
                self._refreshing = False
