"""``--planner wamplan``: wamplan's default planner, MPPI (:mod:`wamplan.planning.mppi`) with its softmax
temperature pinned at ``TEMPERATURE`` (its config, :class:`WamplanConfig`, is in :mod:`wamplan.planning.configs`).

Its settings: 32 candidates (the current mean included) x 4 iterations, initial sigma 0.10 on every action
dimension around the WAM's chunk, white sampling noise, costs normalised by each iteration's range, the
weighted mean as the new mean and the weighted std as the new sigma (MPPI's defaults), temperature 0.1.
Pinning the temperature (in ``configs``) keeps ``wamplan`` the same planner if MPPI's own default ever changes.

It is an ordinary registry entry (a planner class whose config subclass changes defaults), so
``make_planner("wamplan")``, ``EvalConfig(planner="wamplan")`` and every generated option work as for any
planner, and an evaluation directory records all of its settings. The paper's CEM stays ``--planner cem``.
"""

from __future__ import annotations

from wamplan.planning.base import register_planner
from wamplan.planning.configs import DEFAULT_PLANNER, TEMPERATURE, WamplanConfig
from wamplan.planning.mppi import MPPIPlanner

__all__ = ["DEFAULT_PLANNER", "TEMPERATURE", "WamplanConfig", "WamplanPlanner"]


@register_planner(DEFAULT_PLANNER)
class WamplanPlanner(MPPIPlanner):
    """wamplan's default planner: MPPI's search with :class:`WamplanConfig`."""

    config_cls = WamplanConfig
    config: WamplanConfig
