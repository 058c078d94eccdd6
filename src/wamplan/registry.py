"""One registry type for every family that is built by name: policies, WAMs, WAM checkpoint loaders,
encoders, planners, costs and the ``wamplan`` sub-commands (``wamplan.cli.main.COMMANDS``) (lerobot's ``register_subclass`` pattern).

One way to fill them: an entry registers itself with the ``register(name)`` decorator in the module that
defines it, and the registry names the modules holding its built-in entries (``modules``), which it
imports the first time it is read. A plug-in registers the same way, by being imported.
"""

from __future__ import annotations

import importlib
from typing import Callable, Iterable, TypeVar

from wamplan.errors import UserError

T = TypeVar("T")


class Registry(dict):
    """``name -> class or factory``. ``register(name)`` is a decorator; ``lookup(name)`` fails with a
    one-line ``error`` listing the choices. Classes registered with ``set_name`` get ``cls.name = name``.
    Reading the registry (``in``, iteration, ``lookup``, ...) first imports its ``modules``."""

    def __init__(self, kind: str, set_name: bool = False, modules: Iterable[str] = (),
                 error: type[Exception] = UserError):
        super().__init__()
        self.kind, self.set_name, self.error = kind, set_name, error
        self.modules, self._loaded = tuple(modules), not modules

    def register(self, name: str) -> Callable[[T], T]:
        def deco(obj: T) -> T:
            if dict.__contains__(self, name):
                raise ValueError(f"{self.kind} '{name}' is registered twice")
            if self.set_name and isinstance(obj, type):
                obj.name = name  # type: ignore[attr-defined]
            self[name] = obj
            return obj

        return deco

    def load(self) -> "Registry":
        """Import the modules that register the built-in entries (once)."""
        if not self._loaded:
            self._loaded = True  # before importing: those modules read the registry while registering
            for module in self.modules:
                importlib.import_module(module)
        return self

    def lookup(self, name: str):
        if name not in self:
            raise self.error(f"unknown {self.kind} '{name}'; choose one of {sorted(self)}")
        return self[name]

    # reading the registry loads it first
    def __contains__(self, name: object) -> bool:
        return dict.__contains__(self.load(), name)

    def __iter__(self):
        return dict.__iter__(self.load())

    def __len__(self) -> int:
        return dict.__len__(self.load())

    def __getitem__(self, name: str):
        return dict.__getitem__(self.load(), name)

    def keys(self):
        return dict.keys(self.load())

    def values(self):
        return dict.values(self.load())

    def items(self):
        return dict.items(self.load())

    def get(self, name: str, default=None):
        return dict.get(self.load(), name, default)

