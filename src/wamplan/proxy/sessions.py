"""One robot's episode in the proxy (:class:`Session`) and the bounded table of them (:class:`Sessions`).

A session is named by its URL (``/s/<robot>/act``; plain ``/act`` is the session ``default``) and, when a request
carries a RoboArena-style ``session_id``, by that too. A new episode starts on a session's first request, after
``idle_s`` without one, on a request with ``reset: true``, or after ``POST /s/<robot>/reset``. At most
``max_sessions`` are kept; beyond that the least recently used one is dropped (its robot's next request starts a
new episode).
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from concurrent.futures import Future
from typing import Any, Callable

import numpy as np

from wamplan.wam import protocol


class BadRequest(protocol.ProtocolError):
    """A proxy field of the request is malformed (answered 400)."""


def session_name(sid: Any) -> str | None:
    """A request's ``session_id`` as the proxy names it (a string; RoboArena may send a (1,) array), or None;
    BadRequest for anything else, and for a name that starts with ``#`` (the proxy's own connections' names)."""
    if isinstance(sid, np.ndarray) and sid.size == 1:
        sid = sid.reshape(-1)[0].item()
    if isinstance(sid, bytes):
        sid = sid.decode("utf-8", "replace")
    if sid is None:
        return None
    if isinstance(sid, bool) or not isinstance(sid, (str, int, np.integer)):
        raise BadRequest(f"session_id is a {type(sid).__name__}, expected a string")
    sid = str(sid)
    if not sid or sid.startswith("#") or len(sid) > 200:
        raise BadRequest(f"session_id {sid[:40]!r} is empty, over 200 characters or starts with '#'; name the "
                         f"session with a plain string")
    return sid


class Session:
    """The planned policy of one robot's episode and where that episode stands (``step``: the step of its next
    request, as far as known: ``last`` plus what the robot runs of a chunk; ``last``: the step of the chunk answered
    last; ``answered``: the (H, A) chunk answered last, the task's columns). ``lock`` serialises its requests;
    ``pending`` is a plan still running after its budget ran out (the next request waits for it)."""

    def __init__(self, key: str, policy: Any, wam: Any, seed: int = 0):
        self.key, self.policy, self.wam = key, policy, wam
        self.lock = threading.Lock()
        self.pending: Future | None = None
        self.last_seen = time.monotonic()
        self.new_episode(seed)

    def new_episode(self, seed: int = 0) -> None:
        self.policy.reset(seed=seed)
        self.seed, self.step, self.chunks = seed, 0, 0
        self.last = 0  # the step of the chunk answered last
        self.answered: np.ndarray | None = None  # (H, A) the chunk the robot was told to run
        self.announce: str | None = None  # why the episode is new, for the next answer when a request did not say


class Sessions:
    """Sessions by key, made by ``make(key)``; ``get`` says why a session starts a new episode. ``on_forget(session,
    why)`` is told of each session dropped ("dropped") or evicted ("evicted")."""

    def __init__(self, make: Callable[[str], Session], idle_s: float, max_sessions: int,
                 on_forget: Callable[[Session, str], None] | None = None):
        self.make, self.idle_s, self.max_sessions = make, idle_s, max_sessions
        self.on_forget = on_forget
        self._table: OrderedDict[str, Session] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: str) -> tuple[Session, str | None]:
        """The session ``key`` -> (session, why its episode is new: "first-request", "idle", or None)."""
        now = time.monotonic()
        evicted = []
        with self._lock:
            s = self._table.get(key)
            why = None
            if s is None:
                s, why = self.make(key), "first-request"
                self._table[key] = s
                while len(self._table) > self.max_sessions:
                    evicted.append(self._table.popitem(last=False)[1])  # the least recently used
            elif now - s.last_seen > self.idle_s:
                why = "idle"
            self._table.move_to_end(key)
            s.last_seen = now
        for gone in evicted if self.on_forget else ():
            self.on_forget(gone, "evicted")
        return s, why

    def drop(self, key: str) -> bool:
        """Forget session ``key`` (its next request starts a new episode) -> whether it existed."""
        with self._lock:
            gone = self._table.pop(key, None)
        if gone is not None and self.on_forget:
            self.on_forget(gone, "dropped")
        return gone is not None

    def __len__(self) -> int:
        return len(self._table)

    def keys(self) -> list[str]:
        with self._lock:
            return list(self._table)
