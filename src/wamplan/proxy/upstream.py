"""The WAM behind the proxy: an ``/act`` server reached over HTTP, or a WAM loaded in this process.

Both answer an :class:`~wamplan.wam.protocol.ActRequest` with an :class:`~wamplan.wam.protocol.ActResponse` in the
upstream's own fields (:meth:`Upstream.ask`); :class:`UpstreamError` says why an answer could not be had.
:class:`AnsweredWAM` hands an answer already obtained to the planned policy as its WAM's prediction, so the
planning logic (``PlannedPolicy.plan_chunk``) runs unchanged.
"""

from __future__ import annotations

import abc
import os
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlparse, urlunparse

import numpy as np
import requests

from wamplan.envs.spec import Observation, TaskSpec
from wamplan.serving import HEALTH_ROUTE, SECRET_HEADER
from wamplan.wam import protocol
from wamplan.wam.base import WAM, WAMOutput

UPSTREAM_SECRET_ENV = "WAMPLAN_UPSTREAM_SECRET"  # the upstream's shared secret, if it wants one


class UpstreamError(Exception):
    """The upstream gave no usable answer: ``status`` 502 (unreachable, failed, malformed) or 504 (timeout)."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status, self.message = status, message


@dataclass(frozen=True)
class UpstreamShape:
    """What the proxy knows of the upstream before its first answer (None: not known)."""

    chunk_length: int | None
    action_dim: int | None  # columns of its actions
    cameras: tuple[str, ...] | None  # the cameras it predicts
    image_size: int | None  # side of its predicted views (the smallest)
    task: str | None
    view_fields: tuple[str, ...] | None = None  # the answer fields of the views it predicts


def answer_shape(ans: protocol.ActResponse) -> UpstreamShape:
    """What one answer of the upstream shows of it: its chunk length, action size, predicted views and their size."""
    H, A = ans.actions.shape
    sides = [min(img.shape[:2]) for img in ans.future_images.values()]
    return UpstreamShape(chunk_length=int(H), action_dim=int(A), cameras=None, image_size=min(sides) if sides else None,
                         task=None, view_fields=tuple(sorted(ans.future_images)))


class Upstream(abc.ABC):
    shape: UpstreamShape
    where: str

    @abc.abstractmethod
    def ask(self, req: protocol.ActRequest, obs: Observation) -> protocol.ActResponse:
        """The upstream's answer to ``req`` (``obs``: the same request as wamplan's observation)."""

    def alive(self) -> str | None:
        """A check that costs the upstream no inference: None if it still answers at all, else why not."""
        return None

    def close(self) -> None:
        pass


class HttpUpstream(Upstream):
    """An ``/act`` server: Cosmos Policy's ``deploy.py``, ``wamplan wam serve``, another proxy. Its secret, if any,
    comes from ``$WAMPLAN_UPSTREAM_SECRET``. ``shape`` is read from its ``/health`` where it has one (wamplan's)."""

    def __init__(self, url: str, timeout_s: float, chunk_length: int | None = None):
        """``chunk_length``: the chunk length it returns, where its ``/health`` does not report one (what it reports
        wins, so a different ``--chunk-length`` is refused at start-up, not at every request)."""
        self.url, self.timeout_s, self.where = url, timeout_s, f"the upstream WAM at {url}"
        self._session = requests.Session()
        self._session.trust_env = urlparse(url).hostname not in ("127.0.0.1", "localhost", "::1")
        secret = os.environ.get(UPSTREAM_SECRET_ENV)
        self._headers = {**protocol.JSON_HEADERS, **({SECRET_HEADER: secret} if secret else {})}
        self.unreachable: str | None = None  # why the start-up's /health got no answer at all (None: it answered)
        health = self._health()
        self.shape = UpstreamShape(
            chunk_length=health.get("chunk_length") or chunk_length, action_dim=health.get("action_dim"),
            cameras=tuple(health["cameras"]) if health.get("cameras") else None,
            image_size=health.get("image_size"), task=health.get("task"))

    def _health(self) -> dict[str, Any]:
        parts = urlparse(self.url)
        path = parts.path[:-len(protocol.ROUTE)] if parts.path.endswith(protocol.ROUTE) else parts.path
        url = urlunparse(parts._replace(path=path.rstrip("/") + HEALTH_ROUTE))
        try:
            r = self._session.get(url, timeout=min(self.timeout_s, 5.0))
            body = r.json() if r.status_code == 200 else {}
        except (requests.exceptions.ConnectionError, requests.exceptions.Timeout) as e:
            self.unreachable = type(e).__name__  # nothing answered: not up yet, or a wrong host or port
            return {}
        except (requests.exceptions.RequestException, ValueError):
            return {}  # Cosmos Policy's server has no health route: its sizes come from the settings
        return body if isinstance(body, dict) else {}

    def ask(self, req: protocol.ActRequest, obs: Observation) -> protocol.ActResponse:
        body = protocol.encode_request(req).encode()
        try:
            r = self._session.post(self.url, data=body, headers=self._headers, timeout=(5.0, self.timeout_s))
        except requests.exceptions.Timeout as e:
            raise UpstreamError(504, f"{self.where} did not answer within {self.timeout_s:g} s") from e
        except requests.exceptions.RequestException as e:
            raise UpstreamError(502, f"{self.where} is not reachable ({type(e).__name__})") from e
        if r.status_code in (401, 403):
            fix = (f"the secret in ${UPSTREAM_SECRET_ENV} is not its own: set it to the upstream's"
                   if SECRET_HEADER in self._headers else
                   f"it wants a shared secret: start serve with ${UPSTREAM_SECRET_ENV} set to it")
            raise UpstreamError(502, f"{self.where} refused the proxy (HTTP {r.status_code}); {fix}")
        if r.status_code != 200:
            raise UpstreamError(502, f"{self.where} answered HTTP {r.status_code} ({r.text[:200]!r})")
        try:
            return protocol.decode_response(r.content)
        except protocol.ErrorReply as e:
            raise UpstreamError(502, f'{self.where} answered "error" (its log has the reason)') from e
        except protocol.ProtocolError as e:
            raise UpstreamError(502, f"{self.where} sent a malformed answer: {e}") from e

    def alive(self) -> str | None:
        """``GET`` on the ``/act`` route: any HTTP answer (Cosmos Policy's server: 405) means its server runs."""
        timeout = min(self.timeout_s, 3.0)
        try:
            self._session.get(self.url, timeout=timeout)
        except requests.exceptions.Timeout:
            return f"{self.where} did not answer within {timeout:g} s"
        except requests.exceptions.RequestException as e:
            return f"{self.where} is not reachable ({type(e).__name__})"
        return None

    def close(self) -> None:
        self._session.close()


class LocalUpstream(Upstream):
    """A WAM in this process (a checkpoint directory), answering in ``response_map``'s fields."""

    def __init__(self, wam: WAM, response_map: dict[str, str]):
        self.wam, self.response_map, self.where = wam, dict(response_map), f"the WAM '{wam.name}'"
        size = getattr(getattr(wam, "config", None), "image_size", None)
        self.shape = UpstreamShape(chunk_length=int(wam.chunk_length), action_dim=int(wam.action_dim),
                                   cameras=tuple(wam.cameras), image_size=size, task=wam.task.name)

    def ask(self, req: protocol.ActRequest, obs: Observation) -> protocol.ActResponse:
        try:
            out = self.wam.validate(self.wam.predict(obs, req.task_description or self.wam.default_instruction))
        except Exception as e:  # the upstream's failure, whatever it is, is answered as the upstream's
            raise UpstreamError(502, f"{self.where} failed ({type(e).__name__}: {e})") from e
        future = {name: out.images[cam] for cam, name in self.response_map.items() if cam in out.images}
        return protocol.ActResponse(actions=out.actions, future_images=future, value=out.value)

    def close(self) -> None:
        self.wam.close()


def to_output(ans: protocol.ActResponse, task: TaskSpec, response_map: dict[str, str],
              columns: tuple[int, ...]) -> tuple[WAMOutput, list[str]]:
    """The upstream's answer as the planned policy's WAM output: the task's action ``columns`` clipped to [-1, 1],
    the views of ``response_map`` (camera -> answer field) as predicted (the encoder resizes them) -> (output,
    notes saying what was changed). Raises UpstreamError when the answer lacks what planning needs."""
    H, A = ans.actions.shape
    if max(columns) >= A:
        raise UpstreamError(502, f"the upstream returned {A}-D actions; task {task.name} needs columns {list(columns)}")
    actions, note = protocol.clip_actions(ans.actions[:, list(columns)].astype(np.float32))  # (H, A_task)
    notes = [note] if note else []
    images = {}
    for cam, name in response_map.items():
        if name not in ans.future_images:
            raise UpstreamError(502, f"the upstream predicted no '{name}' view (it sent {sorted(ans.future_images)}); "
                                     f"the world model needs camera '{cam}'")
        images[cam] = ans.future_images[name]  # (h, w, 3)
    return WAMOutput(actions=actions, images=images, value=ans.value), notes


class AnsweredWAM(WAM):
    """The planned policy's WAM inside the proxy: ``predict`` returns the answer the session obtained from the
    upstream for the request being handled (:meth:`answer`), once."""

    name = "upstream"

    def __init__(self, task: TaskSpec, chunk_length: int, cameras: tuple[str, ...]):
        self.task = task
        self.chunk_length = int(chunk_length)
        self.cameras = tuple(cameras)
        self._pending: WAMOutput | None = None

    def answer(self, out: WAMOutput) -> None:
        self._pending = out

    def predict(self, obs: Observation, instruction: str) -> WAMOutput:
        if self._pending is None:
            raise RuntimeError("the proxy's WAM was asked for a prediction it was not given")
        out, self._pending = self._pending, None
        return out
