"""Building the planning proxy: the world model loaded, the upstream reached, and the check that the one fits the
other (:func:`check_fit`), refused in one line at start-up.

The check reads what the upstream says of itself (a wamplan server's ``/health``) and what it answers: at start-up
the proxy sends it one rest observation of the request's shape (:func:`rest_request`; Cosmos Policy's server has no
``/health``) and checks the answer's chunk length, action size, predicted views and their size. An upstream that
does not answer then is checked on its first answer (every request and ``/health`` report a misfit until the proxy
is restarted with settings that fit); :func:`unchecked` says which checks wait and why."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from wamplan.envs.spec import Observation, TaskSpec, check_same_task, get_task
from wamplan.errors import UserError
from wamplan.planning.build import PlanningConfig, planned_policy
from wamplan.proxy.app import Proxy, planning_grid
from wamplan.proxy.config import ProxyConfig, ProxyPolicyConfig
from wamplan.proxy.upstream import (AnsweredWAM, HttpUpstream, LocalUpstream, Upstream, UpstreamError, UpstreamShape,
                                    answer_shape)
from wamplan.wam.protocol import ActRequest, resolve_maps


def check_fit(task: TaskSpec, upstream: Upstream, chunk: int, columns: tuple[int, ...], cameras: tuple[str, ...],
              frameskip: int, encoder_size: int | None, world_model: str, shape: UpstreamShape | None = None,
              response_fields: tuple[str, ...] = (), explicit_columns: bool = True) -> None:
    """Refuse, in one line, a world model that does not fit the upstream (task, chunk, actions, cameras, views):
    what ``shape`` shows of it (an answer's; default: ``upstream.shape``, what it says of itself).
    ``response_fields``: the answer fields of the views the world model needs; ``explicit_columns``: the task's
    action ``columns`` were chosen (a profile's ``action_indices``), not assumed to be the upstream's first."""
    s = shape or upstream.shape
    where = f"world model {world_model} does not fit {upstream.where}"
    if s.task is not None:
        try:
            check_same_task(task.name, s.task, upstream.where,
                            f"serve a world model made for '{s.task}' (--world-model), or put a WAM made for "
                            f"'{task.name}' upstream")
        except UserError as e:
            raise UserError(f"{where}: {e}") from e
    if s.chunk_length is not None and s.chunk_length != chunk:
        raise UserError(f"{where}: it returns {s.chunk_length}-step chunks, not {chunk}; drop --chunk-length or fix it")
    longest = max(chunk, s.chunk_length or 0)
    if longest > task.chunk_len:
        raise UserError(f"{where}: it returns {longest}-step chunks; the world model plans chunks of at most "
                        f"{task.chunk_len} steps (task {task.name}'s); put a WAM of that task upstream, or serve a "
                        f"world model made for the upstream's robot")
    if chunk < frameskip:
        raise UserError(f"{where}: its {chunk}-step chunks are shorter than the world model's frameskip {frameskip}; "
                        f"plan with a world model whose frameskip divides the chunk "
                        f"(`wamplan wm train --frameskip {chunk}`)")
    if s.action_dim is not None and max(columns) >= s.action_dim:
        raise UserError(f"{where}: its actions have {s.action_dim} columns, the world model's task {task.name} "
                        f"takes columns {list(columns)}")
    if s.action_dim is not None and s.action_dim != len(columns) and not explicit_columns:
        raise UserError(f"{where}: its actions have {s.action_dim} columns, task {task.name}'s {len(columns)}; the "
                        f"proxy would overwrite columns {list(columns)} of another robot's actions; serve a world "
                        f"model made for the upstream's robot, or name the columns (a profile's action_indices)")
    if s.cameras is not None and any(c not in s.cameras for c in cameras):
        raise UserError(f"{where}: it predicts views of {list(s.cameras)}, the world model needs {list(cameras)}")
    missing = [f for f in response_fields if s.view_fields is not None and f not in s.view_fields]
    if missing:
        raise UserError(f"{where}: it predicts the views {list(s.view_fields or ())}, not {missing} that the world "
                        f"model needs (cameras {list(cameras)}); pick the --profile that names its fields")
    size = s.image_size
    if size is not None and encoder_size is not None and size < encoder_size:
        raise UserError(f"{where}: it predicts {size}-px views, the world model's encoder reads {encoder_size} px "
                        f"(the target would be upsampled); use a world model trained at {size} px or less")


def rest_request(request_map: dict[str, str], task: TaskSpec, size: int, proprio_dim: int) -> tuple[ActRequest,
                                                                                                 Observation]:
    """The start-up probe: a rest observation of the request's shape (black ``size``-px views in the request's
    image fields, a zero proprio of ``proprio_dim``, the task's instruction), as the upstream's request and as the
    world model's observation."""
    images = {name: np.zeros((size, size, 3), np.uint8) for name in request_map}  # (size, size, 3) each
    req = ActRequest(images=images, proprio=np.zeros(proprio_dim, np.float32), task_description=task.instruction)
    obs = Observation(step=0, proprio=np.zeros(task.proprio_dim, np.float32),
                      images={cam: images[name] for name, cam in request_map.items()})
    return req, obs


def unchecked(proxy: Proxy) -> str | None:
    """One line saying which fit checks wait for the upstream's first answer and why (None: all ran)."""
    if proxy.fit_checked:
        return None
    return (f"warning: {proxy.upstream.where} did not answer the start-up probe ({proxy.health.reason}), so its chunk "
            f"length, action size and predicted views are not checked yet: they are checked on its first answer "
            f"(a misfit is then answered to every request); /health answers 503 until it answers")


def check_planning(planning: PlanningConfig, task: TaskSpec) -> None:
    """Refuse, in one line, what the planned policy itself would not: view weights not one per camera of the world
    model's task. The rest of the chunk rules are checked by building one planned policy at start-up
    (``build_proxy``)."""
    planning.cost.check_cameras(task.name, task.cameras)


def build_proxy(cfg: ProxyConfig, upstream: Upstream | None = None, planning: dict[str, Any] | None = None) -> Proxy:
    """The proxy of ``cfg``: the world model loaded, the upstream reached (or ``upstream``), the fit checked.
    ``planning``: :class:`~wamplan.planning.build.PlanningConfig`'s ``planner``, ``planner_config``, ``policy`` and
    ``cost`` (any of them; unset: condition 7's defaults, but for the history: :class:`ProxyPolicyConfig`'s imagined one, what
    lets clients that post only at chunk boundaries be planned), checked against the world model's task and the
    chunk."""
    from wamplan.planning.dynamics import LearnedDynamics, task_name
    from wamplan.wam.base import LEGACY_TASK, load_wam
    from wamplan.wam.cosmos_client import profile_config
    from wamplan.worldmodel.load import load_world_model

    predictor, encoder = load_world_model(cfg.world_model, device=cfg.device, dtype=cfg.wm_dtype)
    dynamics = LearnedDynamics(predictor)
    task = get_task(task_name(dynamics) or LEGACY_TASK)
    plan_cfg = PlanningConfig(**{"policy": ProxyPolicyConfig(), **(planning or {})})
    cameras = tuple(dynamics.cameras or task.cameras)
    profile = cfg.profile
    client = profile_config(profile, task=task.name) if profile else None
    if client is not None:
        request_map, response_map = client.request_map, client.response_map
        columns, profile_chunk = client.action_columns, client.chunk_length
    else:
        request_map, response_map = resolve_maps(cameras)
        columns, profile_chunk = tuple(range(task.action_dim)), None
    missing = [c for c in cameras if c not in response_map]
    if missing:
        raise UserError(f"profile {profile or '(none)'} maps no predicted view to camera(s) {missing} the world "
                        f"model reads")
    response_map = {c: response_map[c] for c in cameras}
    if upstream is None:
        if cfg.upstream_is_url:
            upstream = HttpUpstream(cfg.upstream, cfg.upstream_timeout_s, cfg.chunk_length)
        else:
            upstream = LocalUpstream(load_wam(cfg.upstream, device=cfg.device), response_map)
    size = getattr(encoder, "input_size", None)
    frameskip = getattr(dynamics, "frameskip", None)
    explicit = client is not None and client.action_indices is not None  # else the first A columns, assumed
    fields = tuple(response_map[c] for c in cameras)
    probe = rest_request(request_map, task, (client.send_image_size if client else None) or upstream.shape.image_size
                         or size or 224,
                         (client.proprio_dim if client else None) or task.proprio_dim)
    known = cfg.chunk_length or upstream.shape.chunk_length or profile_chunk
    chunk = known or task.chunk_len

    def fit(shape: UpstreamShape | None = None) -> None:
        check_fit(task, upstream, chunk, columns, cameras, frameskip or chunk, size, cfg.world_model, shape, fields,
                  explicit)

    fit()  # what the upstream says of itself (a wamplan server's /health), before anything is sent to it
    check_planning(plan_cfg, task)
    first, why = None, None  # the upstream's answer to the probe, or why it gave none
    if isinstance(upstream, LocalUpstream):
        pass  # a WAM in this process said its shape itself (upstream.shape), checked above
    else:
        try:
            first = upstream.ask(*probe)
        except UpstreamError as e:
            why = e
    if first is not None:
        chunk = known or first.actions.shape[0]
        fit(answer_shape(first))  # what it answers
    requery = plan_cfg.policy.requery_every or chunk
    if requery > chunk:
        raise UserError(f"--requery-every {requery} is longer than the upstream's {chunk}-step chunk; a robot runs at "
                        f"most the {chunk} actions it was given before asking again")
    if plan_cfg.policy.history == "imagined" and frameskip and requery % frameskip:
        raise UserError(f"--history imagined predicts the world model's frames every {frameskip} steps from a "
                        f"client's last request, and a client that runs {requery} steps of each chunk leaves none on "
                        f"that grid; start serve with --history seen (the in-chunk frames sent in chunk_frames) or "
                        f"with a world model whose frameskip divides {requery}")
    # a session plans from any step on the grid its client's requests and the world model's frames share
    per_session = dataclasses.replace(plan_cfg, policy=dataclasses.replace(
        plan_cfg.policy, requery_every=planning_grid(requery, dynamics)))
    make = lambda wam: planned_policy(wam, dynamics, encoder, per_session, world_models=[cfg.world_model])  # noqa: E731
    make(AnsweredWAM(task, chunk, cameras))  # what only the world model can refuse (a frameskip longer than the
    # chunk, a --requery-every past it) is refused now, once
    proxy = Proxy(cfg, upstream, dynamics, encoder, task, make, request_map, response_map, columns, chunk,
                  requery=requery, probe=probe, fit=fit, imagined=per_session.policy.history == "imagined")
    if why is None:
        proxy.fit_checked = True
        proxy.health.record(True, "it answered the start-up probe" if first is not None else "in process",
                            "start-up probe")
    else:
        proxy.health.failed(why, "start-up probe")
    return proxy
