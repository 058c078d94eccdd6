"""The Cosmos Policy client's named profiles (``--wam-profile NAME``, the proxy's ``--profile``): the field mapping
and sizes of a kind of server, as :class:`~wamplan.wam.cosmos_client.CosmosClientConfig` overrides. Plain data,
so that option parsers list them without loading the client."""

from __future__ import annotations

from typing import Any

_ROBOCASA = dict(request_fields=("front=primary_image", "side=secondary_image", "wrist=wrist_image"),
                 response_fields=("front=future_image", "side=future_image2", "wrist=future_wrist_image"),
                 chunk_length=16, action_indices=(0, 1, 2, 3, 4), proprio_dim=None, send_image_size=224)
# ALOHA's fields are the client's defaults: left unset, they map any task's cameras by position.
_ALOHA = dict(chunk_length=50, proprio_dim=14, send_image_size=224)
PROFILES: dict[str, dict[str, Any]] = {"cosmos-robocasa": _ROBOCASA, "cosmos-aloha": _ALOHA}


def profile_names() -> tuple[str, ...]:
    """``--wam-profile``'s (and ``serve --profile``'s) values: the named client profiles (left out: the client's
    defaults)."""
    return tuple(PROFILES)
