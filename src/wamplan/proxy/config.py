"""The planning proxy's settings, :class:`ProxyConfig`."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlparse, urlunparse

from wamplan.config import check_numbers, field, one_checkpoint, require, with_default
from wamplan.errors import UserError
from wamplan.planning.build import WM_DTYPES
from wamplan.planning.policy_config import PlannedPolicyConfig
from wamplan.serving import DEFAULT_MAX_REQUEST_BYTES, ERROR_MODES
from wamplan.wam.profiles import PROFILES, profile_names

DEFAULT_ROBOT = "default"  # the session of plain /act (and of a WebSocket on /)
PROXY_FIELDS = ("session_id", "reset", "seed", "executed_actions", "chunk_frames")  # read by the proxy, never forwarded


@dataclass(frozen=True)
class ProxyPolicyConfig(PlannedPolicyConfig):
    """The proxy's chunk rules: condition 7's, with the in-chunk history imagined (its clients post only at chunk
    boundaries; frames a client sends in ``chunk_frames`` are used where it sends them)."""

    history: str = with_default(PlannedPolicyConfig, "history", "imagined")


@dataclass(frozen=True)
class ProxyConfig:
    """How the proxy reaches its upstream WAM, plans, keeps sessions and answers failures."""

    upstream: str = field("", "the WAM to plan for: its /act URL (http://HOST:PORT/act) or a local WAM checkpoint "
                              "directory")
    world_model: str = field("", "world model checkpoint directory")
    profile: str = field("", "the upstream's fields and sizes: a client profile (cosmos-robocasa, cosmos-aloha); "
                             "unset: ALOHA's field names mapped onto the world model's cameras by position",
                    choices=profile_names)
    errors: str = field("upstream", "how failures (the client's and the upstream's) are answered: upstream (HTTP 200 "
                                    "and \"error\", as Cosmos Policy's server; use it with upstream clients) or http "
                                    "(4xx/5xx with a one-line reason)", choices=ERROR_MODES)
    budget_ms: float = field(0.0, "milliseconds planning may take once the upstream has answered; later, the "
                                  "upstream's chunk is answered and the wamplan field says why; 0 = no budget")
    idle_s: float = field(300.0, "a session idle this long starts a new episode on its next request")
    max_sessions: int = field(64, "sessions kept at most; the least recently used one is dropped beyond it")
    upstream_timeout_s: float = field(60.0, "seconds to wait for the upstream's answer")
    chunk_length: int | None = field(None, "actions per chunk the upstream returns; unset: its /health's (a wamplan "
                                           "server), its --profile's, or its answer to the start-up probe's")
    ws_fields: str = field("", "openpi WebSocket clients: renames of an observation's keys to the /act fields, "
                               "FROM=TO comma-separated (nested keys joined with /; A+B=proprio joins vectors), e.g. "
                               "images/cam_high=primary_image,state=proprio")
    history_spacing: int = field(12, "steps between the frames of upstream's eval client's proprio_history / "
                                     "images_history (its history_spacing_factor)")
    max_request_bytes: int = field(DEFAULT_MAX_REQUEST_BYTES, "refuse larger /act bodies (HTTP 413) and WebSocket "
                                                              "messages (the connection is closed with code 1009)")
    fit_proprio: bool = field(False, "pad with zeros or truncate a proprio of another length than the world model's "
                                     "(e.g. ALOHA's 14-D qpos), said in each answer's wamplan field; unset: refuse it "
                                     "(HTTP 400; \"error\" in the upstream error mode)")
    device: str = field("auto", "torch device for the world model (and a local upstream)")
    wm_dtype: str = field("float32", "arithmetic of the world model's rollouts in the search: float32, or bfloat16 "
                                     "(faster on a GPU; benchmarks/planner.py --dtypes times both); the cost is "
                                     "computed in float32 either way", choices=WM_DTYPES)
    record: str = field("", "record every session as episodes of an episode store in this directory (boundary views, "
                            "proprio, the actions run; crash-safe), for `wamplan wm train --data DIR`; unset: none")
    record_every: int | None = field(None, "steps between the frames --record keeps (the store's image_every); unset: "
                                           "the chunk (boundary frames only); shorter keeps the chunk_frames a "
                                           "client sends on that grid; a client that runs k steps of each chunk: k")

    def __post_init__(self) -> None:
        check_numbers(self)
        require(bool(self.upstream), "--upstream: name the WAM to plan for (an /act URL or a WAM checkpoint)")
        require("://" not in self.upstream or self.upstream_is_url,
                f"--upstream {self.upstream}: only http:// and https:// URLs are reached (e.g. "
                f"http://HOST:8777/act); or give a local WAM checkpoint directory")
        require(not self.upstream_is_url or urlparse(self.upstream).path not in ("", "/"),
                f"--upstream {self.upstream} names no route; a WAM server answers at /act: pass "
                f"{urlunparse(urlparse(self.upstream)._replace(path='/act'))}")
        require(self.upstream_is_url or Path(self.upstream).exists() or not re.match(r"^[\w.-]+:\d+(/|$)", self.upstream),
                f"--upstream {self.upstream} looks like an address without its scheme; pass http://{self.upstream}")
        require(bool(self.world_model), "--world-model: name a world model checkpoint (from `wamplan wm train`)")
        one_checkpoint(self.world_model, "--world-model")  # several joined by + or commas (an ensemble): one line
        require(not self.profile or self.profile in PROFILES,
                f"--profile: unknown profile '{self.profile}'; profiles are {sorted(PROFILES)}")
        require(self.errors in ERROR_MODES, f"--errors must be one of {list(ERROR_MODES)}, got {self.errors!r}")
        require(self.budget_ms >= 0, f"--budget-ms must be >= 0 (0: no budget), got {self.budget_ms}")
        require(self.idle_s > 0, f"--idle-s must be > 0, got {self.idle_s}")
        require(self.max_sessions >= 1, f"--max-sessions must be >= 1, got {self.max_sessions}")
        require(self.upstream_timeout_s > 0, f"--upstream-timeout-s must be > 0, got {self.upstream_timeout_s}")
        require(self.chunk_length is None or self.chunk_length >= 1,
                f"--chunk-length must be >= 1 (or unset), got {self.chunk_length}")
        require(self.wm_dtype in WM_DTYPES, f"--wm-dtype must be one of {list(WM_DTYPES)}, got {self.wm_dtype!r}")
        require(self.history_spacing >= 1, f"--history-spacing must be >= 1, got {self.history_spacing}")
        parse_ws_fields(self.ws_fields)  # a malformed entry is refused here, in one line
        require(self.max_request_bytes >= 1, f"--max-request-bytes must be >= 1, got {self.max_request_bytes}")
        require(self.record_every is None or self.record_every >= 1,
                f"--record-every must be >= 1 (or unset: the chunk), got {self.record_every}")

    @property
    def upstream_is_url(self) -> bool:
        return self.upstream.lower().startswith(("http://", "https://"))


def parse_ws_fields(spec: str) -> list[tuple[tuple[str, ...], str]]:
    """``"A=x,B+C=proprio"`` -> [(("A",), "x"), (("B", "C"), "proprio")]; UserError on a malformed entry."""
    out = []
    for item in filter(None, (p.strip() for p in spec.split(","))):
        src, eq, dst = item.partition("=")
        sources = tuple(s.strip() for s in src.split("+"))
        if not eq or not dst.strip() or not all(sources):
            raise UserError(f"--ws-fields entry {item!r} is not FROM=TO (e.g. observation/state=proprio, or "
                            f"observation/joint_position+observation/gripper_position=proprio)")
        out.append((sources, dst.strip()))
    return out
