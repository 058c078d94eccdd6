"""Build the policy a command names: a registered policy (expert, noisy-expert, pink) or a WAM
checkpoint directory run open loop. It sits above the WAM layer because it may load a WAM; lower
layers that need a policy by name (``wamplan.data.collect``) take this function as an argument."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from wamplan.errors import UserError
from wamplan.policies import POLICIES, Policy, make_policy


def load_policy(spec: str, instruction: str | None = None, **kwargs: Any) -> Policy:
    """A registered policy name (``kwargs`` go to its constructor), or a directory holding a WAM checkpoint
    (run open loop)."""
    if spec in POLICIES:
        return make_policy(spec, **kwargs)
    if kwargs:
        raise UserError(f"settings {sorted(kwargs)} are for the registered policies, not for '{spec}'")
    if Path(spec).is_dir():
        from wamplan.wam import WAMPolicy, load_wam

        return WAMPolicy(load_wam(spec), instruction=instruction) if instruction else WAMPolicy(load_wam(spec))
    raise UserError(f"unknown policy '{spec}': choose one of {sorted(POLICIES)} or pass a WAM checkpoint directory")
