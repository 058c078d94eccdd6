"""One registry type for every family that is built by name: policies, WAMs, WAM checkpoint loaders,
encoders, planners, costs (lerobot's ``register_subclass`` pattern)."""

from __future__ import annotations

from typing import Callable, TypeVar

from wamplan.errors import UserError

T = TypeVar("T")


class Registry(dict):
    """``name -> class or factory``. ``register(name)`` is a decorator; ``lookup(name)`` fails with a
    one-line error listing the choices. Classes registered with ``set_name`` get ``cls.name = name``."""

    def __init__(self, kind: str, set_name: bool = False):
        super().__init__()
        self.kind, self.set_name = kind, set_name

    def register(self, name: str) -> Callable[[T], T]:
        def deco(obj: T) -> T:
            if name in self:
                raise ValueError(f"{self.kind} '{name}' is registered twice")
            if self.set_name and isinstance(obj, type):
                obj.name = name  # type: ignore[attr-defined]
            self[name] = obj
            return obj

        return deco

    def lookup(self, name: str):
        if name not in self:
            raise UserError(f"unknown {self.kind} '{name}'; choose one of {sorted(self)}")
        return self[name]
