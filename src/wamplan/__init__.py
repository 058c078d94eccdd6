"""wamplan: world-model feedback planning for world action models.

The Python API (:mod:`wamplan.api`) is importable from here, e.g. ``wamplan.load_wam``; its modules are
imported on first use, so ``import wamplan`` (and the command line) stays cheap.
"""

__version__ = "0.1.0"

__all__ = ["ChunkDecision", "CostConfig", "EpisodeResult", "Observation", "PlannedPolicy", "PlannedPolicyConfig", "TaskSpec", "WAM",
           "WAMOutput", "get_task", "load_wam", "make_env", "planned_policy", "register_task", "run_episode", "tasks"]


def __getattr__(name: str):  # PEP 562: the API, imported when first asked for
    if name in __all__:
        from wamplan import api

        return getattr(api, name)
    raise AttributeError(f"module 'wamplan' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
