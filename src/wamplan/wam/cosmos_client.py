"""A Cosmos Policy server (or ``wamplan wam serve``) used as a WAM over HTTP.

    wam = CosmosPolicyClient(CosmosClientConfig(url="http://127.0.0.1:8777/act"))
    out = wam.predict(obs, "insert the cube into the hole")   # WAMOutput, validated

The client adapts wamplan's observation to what the server was trained on (camera -> request field,
proprio length, chunk length, which action columns are wamplan's action) and maps the predicted
views back to wamplan cameras. It acts in the task of its config (``task``, default cube-insertion; ``wam.task``):
the cameras it maps are that task's. Unset fields map the task's cameras by position
(``protocol.default_maps``, as ``wamplan wam serve`` does) and take the task's action size; ``cosmos-robocasa``
names cube-insertion's cameras. Every failure (server
down, timeout, HTTP error, the "error" answer, a malformed or non-finite answer) raises :class:`WAMServerError`
with one line naming the fix.

CLI flags: ``wamplan.config.add_arguments(parser, CosmosClientConfig, prefix="wam_")`` gives
``--wam-url``, ``--wam-timeout-s``, ...; error messages name those flags. A server's shared secret is not a
config field (configs are recorded with results): pass ``secret=`` or set ``$WAMPLAN_ACT_SECRET``; it goes in
the ``X-WAMplan-Secret`` header.

Named profiles (``--wam-profile NAME``, :mod:`wamplan.wam.profiles`) hold the field mapping and sizes of a kind of
server, so that nobody has to spell field names:

* ``cosmos-robocasa``: a Cosmos Policy fine-tuned on ``wamplan data export --format cosmos-policy`` with its
  RoboCasa dataset class and served with RoboCasa observation names (``primary_image`` = front,
  ``secondary_image`` = side, ``wrist_image`` = wrist; predictions ``future_image`` / ``future_image2`` /
  ``future_wrist_image``), 16-step chunks of wamplan's 5-D actions, 10-D proprio, 224 px views sent. Upstream's
  ``deploy.py`` serves it with ``--suite robocasa --num_wrist_images 1 --num_third_person_images 2 --chunk_size 16``
  and a constants entry checked before its platform checks (docs/cosmos-policy.md).
* ``cosmos-aloha``: a server speaking ALOHA's ``deploy.py`` fields (``primary_image``, ``left_wrist_image``,
  ``right_wrist_image``; ``future_image``, ``future_wrist_image``, ``future_wrist_image2``), 50-step chunks,
  proprio padded to 14-D, 224 px views sent, wamplan's action in columns 0-4.
"""

from __future__ import annotations

import dataclasses
import os
import time
import uuid
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlparse

import numpy as np
import requests
import urllib3

from wamplan.config import ConfigError, check_numbers, field, require, to_dict
from wamplan.envs.spec import TASKS, Observation, get_task, require_images
from wamplan.serving import SECRET_ENV, SECRET_HEADER
from wamplan.wam import protocol
from wamplan.wam.base import WAM, WAMError, WAMOutput, WAMOutputError, WAMServerError, register_wam
from wamplan.wam.profiles import PROFILES

FLAG_PREFIX = "--wam-"


def _flag(name: str) -> str:
    return FLAG_PREFIX + name.replace("_", "-")


def _pairs(items: tuple[str, ...], option: str, cameras: tuple[str, ...]) -> list[tuple[str, str]]:
    """``items`` ("CAMERA=FIELD", ...) as (camera, field) pairs; one line for a camera not among ``cameras``."""
    out = []
    for item in items:
        cam, sep, name = item.partition("=")
        require(bool(sep and cam and name),
                f"{_flag(option)}: '{item}' is not CAMERA=FIELD (e.g. front=primary_image)")
        require(cam in cameras,
                f"{_flag(option)}: unknown camera '{cam}' in '{item}'; the task's cameras are {list(cameras)}")
        out.append((cam, name))
    return out


@dataclass(frozen=True)
class CosmosClientConfig:
    """How to reach a Cosmos Policy /act server and adapt wamplan's observations to it."""

    task: str = field("cube-insertion", "the task the served model acts in (its cameras are the ones mapped)",
                      listed=lambda: TASKS)
    url: str = field(f"http://127.0.0.1:{protocol.DEFAULT_PORT}{protocol.ROUTE}", "the server's /act endpoint")
    request_fields: tuple[str, ...] | None = field(
        None, "CAMERA=FIELD: which camera of the task fills each request image (all three fields are required); "
        "unset: the task's cameras in order fill primary_image, left_wrist_image, right_wrist_image (the last "
        "camera fills any fields left over)")
    response_fields: tuple[str, ...] | None = field(
        None, "CAMERA=FIELD: which predicted future image becomes each camera's target; unset: the task's cameras "
        "in order take future_image, future_wrist_image, future_wrist_image2")
    chunk_length: int = field(16, "actions per chunk the server returns (H); the images are for t + H")
    action_indices: tuple[int, ...] | None = field(
        None, "columns of the server's actions that form the task's action; unset: the first A columns, A the "
        "task's action size (the cube's 5: dx, dy, dz, dyaw, gripper)")
    clip_actions: bool = field(True, "clip actions into [-1, 1] (sampled actions can overshoot slightly); "
                               "off: an out-of-range action is an error")
    proprio_dim: int | None = field(None, "proprio length the server expects (truncate or pad the task's "
                                    "proprio, the cube's 10-D); None sends it unchanged")
    proprio_pad: float = field(0.0, "value used to pad proprio up to proprio_dim")
    send_image_size: int | None = field(None, "resize camera images to this square size before sending; "
                                        "None sends them as rendered")
    image_size: int | None = field(None, "resize predicted images to this square size; None keeps the server's")
    timeout_s: float = field(60.0, "seconds to wait for one answer")
    connect_timeout_s: float = field(5.0, "seconds to wait for a connection")
    retries: int = field(2, "extra attempts when the server cannot be reached (not after a timeout)")
    backoff_s: float = field(0.5, "wait before the first retry; doubles after each")
    send_chunk_frames: tuple[int, ...] = field(
        (), "in-chunk step offsets (1..H-1) whose frames go with the next request as chunk_frames, with reset and "
        "the episode seed on an episode's first request: what a wamplan planning proxy (`wamplan serve`) needs to "
        "plan with a world model whose frameskip is shorter than the chunk (4 8 12 for the shipped one); empty: none")

    def __post_init__(self) -> None:
        check_numbers(self)
        get_task(self.task)  # one line naming the registered tasks if unknown
        require(self.url.startswith(("http://", "https://")),
                f"{_flag('url')} must be an http(s) URL such as http://127.0.0.1:8777/act, got '{self.url}'")
        n_fields = len(protocol.DEFAULT_REQUEST_MAP)
        positional = self.request_fields is None or self.response_fields is None
        require(not positional or len(self.cameras) <= n_fields,
                f"task {self.task} has {len(self.cameras)} cameras {list(self.cameras)} but a request carries "
                f"{n_fields} images; choose them with {_flag('request_fields')} and {_flag('response_fields')}")
        req = _pairs(self.request_pairs, "request_fields", self.cameras)
        names = sorted(n for _, n in req)
        require(any(names == sorted(fs) for fs in protocol.REQUEST_IMAGE_FIELD_SETS),
                f"{_flag('request_fields')} must fill each field of one of {[list(fs) for fs in protocol.REQUEST_IMAGE_FIELD_SETS]} "
                f"exactly once, got {list(self.request_pairs)}")
        resp = _pairs(self.response_pairs, "response_fields", self.cameras)
        require(len(resp) > 0, f"{_flag('response_fields')} must map at least one camera")
        cams = [c for c, _ in resp]
        require(len(set(cams)) == len(cams),
                f"{_flag('response_fields')} maps a camera twice: {list(self.response_pairs)}")
        for _, name in resp:
            require(name in protocol.KNOWN_RESPONSE_IMAGE_FIELDS,
                    f"{_flag('response_fields')}: unknown field '{name}'; Cosmos Policy predicts "
                    f"{list(protocol.KNOWN_RESPONSE_IMAGE_FIELDS)}")
        require(self.chunk_length >= 1, f"{_flag('chunk_length')} must be >= 1, got {self.chunk_length}")
        cols = self.action_columns
        require(len(cols) >= 1 and min(cols) >= 0 and len(set(cols)) == len(cols),
                f"{_flag('action_indices')} must be distinct non-negative column indices, got {cols}")
        for name in ("proprio_dim", "send_image_size", "image_size"):
            v = getattr(self, name)
            require(v is None or v >= 1, f"{_flag(name)} must be >= 1 (or unset), got {v}")
        require(self.timeout_s > 0 and self.connect_timeout_s > 0,
                f"{_flag('timeout_s')} and {_flag('connect_timeout_s')} must be > 0")
        require(self.retries >= 0, f"{_flag('retries')} must be >= 0, got {self.retries}")
        require(self.backoff_s >= 0, f"{_flag('backoff_s')} must be >= 0, got {self.backoff_s}")
        offs = self.send_chunk_frames
        require(all(0 < o < self.chunk_length for o in offs) and len(set(offs)) == len(offs),
                f"{_flag('send_chunk_frames')} must be distinct step offsets in 1..{self.chunk_length - 1}, got "
                f"{list(offs)}")

    @property
    def cameras(self) -> tuple[str, ...]:
        """The task's cameras, the ones the fields may map."""
        return get_task(self.task).cameras

    @property
    def request_pairs(self) -> tuple[str, ...]:
        """``request_fields``, or (unset) the task's cameras mapped by position (``protocol.default_maps``)."""
        if self.request_fields is not None:
            return self.request_fields
        return tuple(f"{cam}={name}" for name, cam in protocol.default_maps(self.cameras)[0].items())

    @property
    def response_pairs(self) -> tuple[str, ...]:
        """``response_fields``, or (unset) the task's cameras mapped by position (``protocol.default_maps``)."""
        if self.response_fields is not None:
            return self.response_fields
        return tuple(f"{cam}={name}" for cam, name in protocol.default_maps(self.cameras)[1].items())

    @property
    def action_columns(self) -> tuple[int, ...]:
        """``action_indices``, or (unset) the first A columns, A the task's action size."""
        if self.action_indices is not None:
            return self.action_indices
        return tuple(range(get_task(self.task).action_dim))

    @property
    def request_map(self) -> dict[str, str]:
        """request field -> camera."""
        return {name: cam for cam, name in _pairs(self.request_pairs, "request_fields", self.cameras)}

    @property
    def response_map(self) -> dict[str, str]:
        """camera -> response field."""
        return dict(_pairs(self.response_pairs, "response_fields", self.cameras))


def profile_config(profile: str = "", **overrides: Any) -> CosmosClientConfig:
    """The client config of a named profile (``""``: the plain defaults), with ``overrides`` on top."""
    if profile and profile not in PROFILES:
        raise ConfigError(f"{_flag('profile')}: unknown profile '{profile}'; profiles are {sorted(PROFILES)}")
    known = {f.name for f in dataclasses.fields(CosmosClientConfig)}
    unknown = sorted(set(overrides) - known)
    require(not unknown, f"CosmosPolicyClient: unknown option(s) {unknown}; known: {sorted(known)}")
    kw = {**PROFILES.get(profile, {}), **{k: tuple(v) if isinstance(v, list) else v for k, v in overrides.items()}}
    task = kw.get("task", CosmosClientConfig.task)
    cameras = get_task(task).cameras
    named = [item.partition("=")[0] for k in ("request_fields", "response_fields") if k not in overrides
             for item in PROFILES.get(profile, {}).get(k, ())]  # cameras the profile itself names
    foreign = [c for c in dict.fromkeys(named) if c not in cameras]
    require(not foreign, f"{_flag('profile')} {profile} names cube-insertion's cameras, not task {task}'s (unknown "
                         f"camera '{foreign[0] if foreign else ''}'; the task's cameras are {list(cameras)}); leave it "
                         f"out to map the task's cameras by position")
    return CosmosClientConfig(**kw)


def resize_image(img: np.ndarray, size: int) -> np.ndarray:
    """(h, w, 3) uint8 -> (size, size, 3) uint8, bilinear with antialiasing."""
    if img.shape[0] == size and img.shape[1] == size:
        return img
    import torch
    import torch.nn.functional as F

    x = torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1)[None].float()  # (1, 3, h, w)
    y = F.interpolate(x, size=(size, size), mode="bilinear", antialias=True, align_corners=False)  # (1, 3, s, s)
    return y[0].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).numpy()  # (s, s, 3)


def _short_reason(e: requests.exceptions.ConnectionError, connect_timeout_s: float) -> str:
    text = str(e)
    if isinstance(e, requests.exceptions.ConnectTimeout):
        return f"no connection within {connect_timeout_s:g} s"
    for needle, reason in (("Connection refused", "connection refused"),
                           ("Name or service not known", "unknown host"),
                           ("nodename nor servname", "unknown host"),
                           ("Connection reset", "connection reset"),
                           ("RemoteDisconnected", "the server closed the connection"),
                           ("Connection aborted", "the connection was aborted")):
        if needle in text:
            return reason
    return text[:160]


def _never_connected(e: requests.exceptions.ConnectionError) -> bool:
    """Whether the request never reached the server (refused, or the connection timed out), so resending it cannot
    repeat it."""
    cause = getattr(e.args[0] if e.args else None, "reason", None)
    return isinstance(e, requests.exceptions.ConnectTimeout) or isinstance(cause, urllib3.exceptions.NewConnectionError)


def _reason(resp: requests.Response) -> str:
    """The one-line reason of a wamplan server's refusal (``{"error": "..."}``), or "" for any other body."""
    try:
        body = resp.json()
    except ValueError:
        return ""
    reason = body.get("error") if isinstance(body, dict) else None
    return " ".join(str(reason).split())[:400] if reason else ""


@register_wam("cosmos")
class CosmosPolicyClient(WAM):
    """A WAM served over the Cosmos Policy /act protocol. ``profile`` (a name in ``PROFILES``) gives the
    config when none is passed; ``overrides`` replace config fields; ``secret`` (default:
    ``$WAMPLAN_ACT_SECRET``) is sent with every request when set."""

    def __init__(self, config: CosmosClientConfig | None = None, *, profile: str = "", session: Any = None,
                 secret: str | None = None, **overrides: Any):
        require(config is None or not profile, "CosmosPolicyClient: pass a config or a profile, not both")
        base = config if config is not None else profile_config(profile)
        if overrides:
            known = {f.name for f in dataclasses.fields(CosmosClientConfig)}
            unknown = sorted(set(overrides) - known)
            require(not unknown, f"CosmosPolicyClient: unknown option(s) {unknown}; known: {sorted(known)}")
            base = dataclasses.replace(base, **{k: tuple(v) if isinstance(v, list) else v
                                                for k, v in overrides.items()})
        self.config = base
        self.task = base.task
        self.chunk_length = base.chunk_length
        self.action_dim = len(base.action_columns)
        self.cameras = tuple(base.response_map)
        self._request_map = base.request_map  # field -> camera
        self._response_map = base.response_map  # camera -> field
        if session is None:
            session = requests.Session()
            # A proxy from the environment must not capture a server on this machine.
            session.trust_env = urlparse(base.url).hostname not in ("127.0.0.1", "localhost", "::1")
        self._session = session
        secret = secret if secret is not None else os.environ.get(SECRET_ENV)
        self._headers = {**protocol.JSON_HEADERS, **({SECRET_HEADER: secret} if secret else {})}
        self.attempts_made = 0  # HTTP attempts of the last query (diagnostics, tests)
        self.frame_offsets = base.send_chunk_frames
        self._session_id = uuid.uuid4().hex[:12]  # sent with send_chunk_frames: one proxy session a client
        self.begin_episode()

    def begin_episode(self, seed: int | None = None) -> None:
        self.reset()
        if self.frame_offsets:
            self._episode_start["seed"] = int(seed or 0)

    def reset(self) -> None:
        """A new episode: with ``send_chunk_frames``, the next request carries ``reset`` (and the seed of
        :meth:`begin_episode`), and every request this client's ``session_id``, so that several clients (an
        evaluation's workers) keep their episodes apart behind one proxy URL."""
        self._frames: dict[str, dict[str, Any]] = {}  # offset -> the fields of the frame seen there
        self._episode_start: dict[str, Any] = {"reset": True} if self.frame_offsets else {}

    def observe(self, obs: Observation) -> None:
        images, proprio = self._fields(obs)
        self._frames[str(obs.step % self.chunk_length)] = {**images, "proprio": proprio}

    @property
    def _where(self) -> str:
        return f"Cosmos Policy server at {self.config.url}"

    def config_dict(self) -> dict[str, Any]:
        """The config with the mapping in use (unset fields resolved for the task)."""
        cfg = self.config
        used = dataclasses.replace(cfg, request_fields=cfg.request_pairs, response_fields=cfg.response_pairs,
                                   action_indices=cfg.action_columns)
        return {"name": self.name, **to_dict(used)}

    def close(self) -> None:
        self._session.close()

    # -- request -------------------------------------------------------------------------------------
    def _request(self, obs: Observation, instruction: str) -> protocol.ActRequest:
        images, proprio = self._fields(obs)
        extra: dict[str, Any] = {}
        if self.frame_offsets:  # what a planning proxy reads (cleared in predict once the answer is read)
            extra = {**self._episode_start, "session_id": self._session_id}
            if obs.step % self.chunk_length == 0 and obs.step > 0:
                extra["chunk_frames"] = dict(self._frames)
        return protocol.ActRequest(images=images, proprio=proprio, task_description=instruction, extra=extra)

    def _fields(self, obs: Observation) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """The request's image fields ((H, W, 3) uint8 each) and (P,) proprio for ``obs``."""
        cfg = self.config
        if obs.images is None:
            raise WAMError(f"the observation at step {obs.step} has no images; the Cosmos client needs "
                           f"{sorted(set(self._request_map.values()))}")
        images = {}
        for name, cam in self._request_map.items():
            if cam not in obs.images:
                raise WAMError(f"the observation has no '{cam}' image (has {sorted(obs.images)}); render it or "
                               f"change {_flag('request_fields')}")
            require_images(obs, [cam], "the Cosmos client")
            img = obs.images[cam]  # (H, W, 3) uint8
            images[name] = resize_image(img, cfg.send_image_size) if cfg.send_image_size else img
        proprio = np.asarray(obs.proprio, dtype=np.float32).reshape(-1)  # (P,)
        if not np.isfinite(proprio).all():
            raise WAMError(f"the observation at step {obs.step} has non-finite proprio {proprio}; "
                           f"check the environment's state")
        if cfg.proprio_dim is not None:
            out = np.full(cfg.proprio_dim, cfg.proprio_pad, dtype=np.float32)  # (P,)
            n = min(cfg.proprio_dim, proprio.shape[0])
            out[:n] = proprio[:n]
            proprio = out
        return images, proprio

    # -- transport -----------------------------------------------------------------------------------
    def _post(self, body: bytes) -> requests.Response:
        cfg = self.config
        attempts = cfg.retries + 1
        reason = ""
        for attempt in range(attempts):
            self.attempts_made = attempt + 1
            try:
                return self._session.post(cfg.url, data=body, headers=self._headers,
                                          timeout=(cfg.connect_timeout_s, cfg.timeout_s))
            except requests.exceptions.ConnectionError as e:  # refused, reset, connect timeout: retry
                reason = _short_reason(e, cfg.connect_timeout_s)
                if self.frame_offsets and not _never_connected(e):
                    # a proxy that already took this boundary would take a repeat as the next one
                    raise WAMServerError(f"{self._where} dropped the connection ({reason}); not retried, as a "
                                         f"planning proxy may have taken the request already") from e
                if attempt + 1 < attempts:
                    time.sleep(cfg.backoff_s * 2 ** attempt)
            except requests.exceptions.Timeout as e:  # read timeout: the server is busy; do not pile on
                raise WAMServerError(f"{self._where} did not answer within {cfg.timeout_s:g} s; raise "
                                     f"{_flag('timeout_s')} or check that the server is not stuck") from e
            except requests.exceptions.RequestException as e:
                raise WAMServerError(f"request to {self._where} failed ({type(e).__name__}: {str(e)[:160]}); "
                                     f"check {_flag('url')}") from e
        raise WAMServerError(f"{self._where} is not reachable ({reason}, {attempts} attempt(s)); "
                             f"start it or pass {_flag('url')}")

    # -- answer --------------------------------------------------------------------------------------
    def _decode(self, resp: requests.Response, sent_proprio: int) -> protocol.ActResponse:
        reason = _reason(resp)  # a wamplan server says what was wrong: {"error": "..."}
        if resp.status_code == 404:
            raise WAMServerError(f"{self._where} has no such route (HTTP 404); Cosmos Policy serves POST "
                                 f"{protocol.ROUTE}: check {_flag('url')}")
        if resp.status_code == 401:
            raise WAMServerError(f"{self._where} refused the request (HTTP 401: wrong or missing shared secret); "
                                 f"set ${SECRET_ENV} to the secret the server was started with")
        if resp.status_code == 413:
            raise WAMServerError(f"{self._where} refused the request as too large (HTTP 413); send smaller "
                                 f"images (this client's send_image_size, now {self.config.send_image_size}; the "
                                 f"--wam-profile presets send 224 px) or raise the server's --max-request-mb")
        if resp.status_code in (400, 422) and reason:
            raise WAMServerError(f"{self._where} refused the request (HTTP {resp.status_code}: {reason}); check that "
                                 f"it serves this task: these cameras, {sent_proprio}-D proprio (see "
                                 f"{_flag('profile')})")
        if resp.status_code != 200:
            said = reason or repr(resp.text[:120])
            raise WAMServerError(f"{self._where} answered HTTP {resp.status_code} ({said}); "
                                 f"check the server's log and {_flag('url')}")
        try:
            return protocol.decode_response(resp.content)
        except protocol.ErrorReply as e:
            raise WAMServerError(f"{self._where} answered \"error\" (it failed on this request; its log has the "
                                 f"traceback); check that it was started for these cameras, {sent_proprio}-D "
                                 f"proprio (see {_flag('proprio_dim')}) and this task") from e
        except protocol.ProtocolError as e:
            raise WAMServerError(f"{self._where} sent a malformed answer: {e}; check that {_flag('url')} is a "
                                 f"Cosmos Policy /act server") from e

    def _output(self, ans: protocol.ActResponse) -> WAMOutput:
        cfg = self.config
        H, A_srv = ans.actions.shape
        if H != cfg.chunk_length:
            raise WAMServerError(f"{self._where} returned {H}-step chunks but {_flag('chunk_length')} is "
                                 f"{cfg.chunk_length}; pass {_flag('chunk_length')} {H} or serve a model "
                                 f"trained with {cfg.chunk_length}-step chunks")
        cols = list(cfg.action_columns)
        if max(cols) >= A_srv:
            raise WAMServerError(f"{self._where} returned {A_srv}-D actions but {_flag('action_indices')} "
                                 f"{cols} needs column {max(cols)}; pick "
                                 f"columns below {A_srv}")
        actions = ans.actions[:, cols].astype(np.float32)  # (H, A)
        if cfg.clip_actions:
            actions = np.clip(actions, -1.0, 1.0)
        images = {}
        for cam, name in self._response_map.items():
            if name not in ans.future_images:
                raise WAMServerError(f"{self._where} returned no '{name}' image (it sent "
                                     f"{sorted(ans.future_images)}); map only those in {_flag('response_fields')}")
            img = ans.future_images[name]  # (h, w, 3)
            images[cam] = resize_image(img, cfg.image_size) if cfg.image_size else img
        return WAMOutput(actions=actions, images=images, value=ans.value)

    def predict(self, obs: Observation, instruction: str) -> WAMOutput:
        t0 = time.perf_counter()
        req = self._request(obs, instruction)
        body = protocol.encode_request(req).encode()
        t_post = time.perf_counter()
        resp = self._post(body)
        http_s = time.perf_counter() - t_post
        ans = self._decode(resp, sent_proprio=req.proprio.shape[0])
        out = self._output(ans)
        self._episode_start, self._frames = {}, {}  # delivered: the next request starts afresh
        try:
            self.validate(out)
        except WAMOutputError as e:
            raise WAMServerError(f"{self._where}: {e}") from e
        out.timing = {"query_s": time.perf_counter() - t0, "http_s": http_s}
        out.extras = {"attempts": self.attempts_made, "url": self.config.url}
        if "planned" in ans.wamplan:  # a planning proxy's report: planned, or why the upstream's chunk ran
            out.extras["proxy"] = {"planned": bool(ans.wamplan["planned"]), "open_loop": ans.wamplan.get("open_loop")}
        return out
