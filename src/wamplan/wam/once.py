"""A WAM wrapper that queries its inner WAM once per step and hands every caller that same output, so several
policies driven side by side at one boundary (the fidelity diagnostic, the mechanism picture) see one chunk
and one target even from a stochastic WAM."""

from __future__ import annotations

from typing import Any

from wamplan.envs.spec import Observation
from wamplan.wam.base import WAM, WAMOutput


class OnceWAM(WAM):
    """Queries ``inner`` once per step of an episode and hands every caller that same output."""

    def __init__(self, inner: WAM):
        self.inner = inner
        self.name = inner.name
        self.task = inner.task
        self.chunk_length, self.action_dim = inner.chunk_length, inner.action_dim
        self.cameras, self.default_instruction = inner.cameras, inner.default_instruction
        self._out: dict[int, WAMOutput] = {}

    def predict(self, obs: Observation, instruction: str) -> WAMOutput:
        if obs.step not in self._out:
            self._out = {obs.step: self.inner.validate(self.inner.predict(obs, instruction))}
        return self._out[obs.step]

    @property
    def last(self) -> WAMOutput | None:
        """The output of the latest step queried (None before the first query of an episode)."""
        return next(iter(self._out.values()), None)

    def reset(self) -> None:
        """A no-op: every PlannedPolicy resets its WAM, so the driver resets the inner WAM itself, once."""

    def new_episode(self) -> None:
        self.inner.reset()
        self._out = {}

    def config_dict(self) -> dict[str, Any]:
        return self.inner.config_dict()
