"""Building the planning proxy: the world model loaded, the upstream reached, and the check that the one fits the
other (:func:`check_fit`), refused in one line at start-up."""

from __future__ import annotations

from typing import Any

from wamplan.config import ensemble_members
from wamplan.envs.spec import TaskSpec, check_same_task, get_task
from wamplan.errors import UserError
from wamplan.planning.build import PlanningConfig, planned_policy
from wamplan.proxy.app import Proxy
from wamplan.proxy.config import ProxyConfig
from wamplan.proxy.upstream import AnsweredWAM, HttpUpstream, LocalUpstream, Upstream
from wamplan.wam.protocol import resolve_maps


def check_fit(task: TaskSpec, upstream: Upstream, chunk: int, columns: tuple[int, ...], cameras: tuple[str, ...],
              frameskip: int, encoder_size: int | None, world_model: str) -> None:
    """Refuse, in one line, a world model that does not fit the upstream (task, chunk, actions, cameras, views)."""
    s = upstream.shape
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
    if chunk < frameskip:
        raise UserError(f"{where}: its {chunk}-step chunks are shorter than the world model's frameskip {frameskip}; "
                        f"plan with a world model whose frameskip divides the chunk "
                        f"(`wamplan wm train --frameskip {chunk}`)")
    if s.action_dim is not None and max(columns) >= s.action_dim:
        raise UserError(f"{where}: its actions have {s.action_dim} columns, the world model's task {task.name} "
                        f"takes columns {list(columns)}")
    if s.cameras is not None and any(c not in s.cameras for c in cameras):
        raise UserError(f"{where}: it predicts views of {list(s.cameras)}, the world model needs {list(cameras)}")
    size = s.image_size
    if size is not None and encoder_size is not None and size < encoder_size:
        raise UserError(f"{where}: it predicts {size}-px views, the world model's encoder reads {encoder_size} px "
                        f"(the target would be upsampled); use a world model trained at {size} px or less")


def check_planning(planning: PlanningConfig, task: TaskSpec) -> None:
    """Refuse, in one line, what the planned policy itself would not: view weights not one per camera of the world
    model's task. The rest of the chunk rules are checked by building one planned policy at start-up
    (``build_proxy``)."""
    planning.cost.check_cameras(task.name, task.cameras)


def build_proxy(cfg: ProxyConfig, upstream: Upstream | None = None, planning: dict[str, Any] | None = None) -> Proxy:
    """The proxy of ``cfg``: the world model loaded, the upstream reached (or ``upstream``), the fit checked.
    ``planning``: :class:`~wamplan.planning.build.PlanningConfig`'s ``planner``, ``planner_config``, ``policy`` and
    ``cost`` (any of them; unset: condition 7's defaults), checked against the world model's task and the chunk."""
    from wamplan.planning.dynamics import learned_dynamics, task_name
    from wamplan.wam.base import LEGACY_TASK, load_wam
    from wamplan.wam.cosmos_client import profile_config
    from wamplan.worldmodel.load import load_world_model

    paths = [p for p in ensemble_members(cfg.world_model) if p]
    dynamics, encoder = learned_dynamics([load_world_model(p, device=cfg.device, dtype=cfg.wm_dtype) for p in paths])
    task = get_task(task_name(dynamics) or LEGACY_TASK)
    plan_cfg = PlanningConfig(**(planning or {}))
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
    chunk = cfg.chunk_length or upstream.shape.chunk_length or profile_chunk or task.chunk_len
    size = getattr(encoder, "input_size", None)
    check_fit(task, upstream, chunk, columns, cameras, getattr(dynamics, "frameskip", chunk), size, cfg.world_model)
    check_planning(plan_cfg, task)
    make = lambda wam: planned_policy(wam, dynamics, encoder, plan_cfg, world_models=paths)  # noqa: E731
    make(AnsweredWAM(task, chunk, cameras))  # what only the world model can refuse (a pose term, an ensemble's
    # disagreement, a frameskip longer than the chunk) is refused now, once, not on every robot's first request
    return Proxy(cfg, upstream, dynamics, encoder, task, make, request_map, response_map, columns, chunk)
