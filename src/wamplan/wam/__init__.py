"""World action models: the interface, the registry, WAM-as-policy, and the Cosmos Policy /act protocol
(``protocol``, the HTTP client ``cosmos_client`` and the server ``server``, imported on demand)."""

from wamplan.wam.base import (
    WAM,
    WAMError,
    WAMOutput,
    WAMOutputError,
    WAMPolicy,
    WAMServerError,
    load_wam,
    make_wam,
    register_wam,
    register_wam_loader,
    validate_wam_output,
)

__all__ = [
    "WAM",
    "WAMError",
    "WAMOutput",
    "WAMOutputError",
    "WAMPolicy",
    "WAMServerError",
    "load_wam",
    "make_wam",
    "register_wam",
    "register_wam_loader",
    "validate_wam_output",
]
