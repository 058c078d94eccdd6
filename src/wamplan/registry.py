"""One registry type for every family that is built by name: policies, WAMs, WAM checkpoint loaders,
encoders, planners, costs and the ``wamplan`` sub-commands (``wamplan.cli.main.COMMANDS``) (lerobot's ``register_subclass`` pattern).

One way to fill them: an entry registers itself with the ``register(name)`` decorator in the module that
defines it, and the registry names the modules holding its built-in entries (``modules``), which it
imports the first time it is read. A plug-in registers the same way, by being imported: a registry with an
entry-point ``group`` (``wamplan.tasks`` for tasks) also imports, on that first read, the module each installed
distribution names in that group, in every process that reads it (spawned workers too).

A plug-in that fails to import, or registers a name that is already taken, is left out whole (none of its names
stay), with one line naming its distribution and the problem: on stderr in the process that is not a worker,
and in the error of a lookup that finds no such name.
"""

from __future__ import annotations

import importlib
import sys
from typing import Callable, Iterable, TypeVar

from wamplan.errors import UserError

T = TypeVar("T")


class DuplicateName(ValueError):
    """``register(name)`` of a name the registry already has."""


class Registry(dict):
    """``name -> class or factory``. ``register(name)`` is a decorator; ``lookup(name)`` fails with a
    one-line ``error`` listing the choices. Classes registered with ``set_name`` get ``cls.name = name``.
    Reading the registry (``in``, iteration, ``lookup``, ...) first imports its ``modules``, then the plug-ins
    of its entry-point ``group``; ``problems`` holds one line per plug-in left out."""

    def __init__(self, kind: str, set_name: bool = False, modules: Iterable[str] = (),
                 error: type[Exception] = UserError, group: str | None = None):
        super().__init__()
        self.kind, self.set_name, self.error, self.group = kind, set_name, error, group
        self.modules, self._loaded = tuple(modules), not (modules or group)
        self.problems: list[str] = []

    def register(self, name: str) -> Callable[[T], T]:
        def deco(obj: T) -> T:
            if dict.__contains__(self, name):
                raise DuplicateName(f"{self.kind} '{name}' is registered twice")
            if self.set_name and isinstance(obj, type):
                obj.name = name  # type: ignore[attr-defined]
            self[name] = obj
            return obj

        return deco

    def load(self) -> "Registry":
        """Import the modules that register the built-in entries, then the plug-ins (once)."""
        if not self._loaded:
            self._loaded = True  # before importing: those modules read the registry while registering
            for module in self.modules:
                importlib.import_module(module)
            if self.group:
                self._load_plugins()
        return self

    def _load_plugins(self) -> None:
        import multiprocessing
        from importlib.metadata import entry_points

        for ep in sorted(entry_points(group=self.group), key=lambda ep: (ep.name, ep.value)):
            before = set(dict.keys(self))
            try:
                ep.load()
                continue
            except DuplicateName as e:
                problem = f"registers a name already taken ({e})"
            except Exception as e:  # whatever the plug-in's import raised: the line says what
                problem = f"failed to import ({type(e).__name__}: {e})"
            for name in set(dict.keys(self)) - before:  # left out whole
                dict.__delitem__(self, name)
            dist = ep.dist.name  # set by entry_points()
            line = (f"{self.kind} plug-in '{ep.name} = {ep.value}' of distribution '{dist}' {problem}; it is left "
                    f"out (fix or uninstall {dist})")
            self.problems.append(line)
            if multiprocessing.parent_process() is None:  # a spawned worker's parent has said it already
                print(f"wamplan: warning: {line}", file=sys.stderr)

    def lookup(self, name: str):
        if name not in self:
            left_out = "".join(f"; {p}" for p in self.problems)
            plug = (f"; a {self.kind} of your own must be registered where every command sees it: in a module an "
                    f"installed package names in the entry-point group '{self.group}' (README, \"Other tasks\")"
                    if self.group and not left_out else "")
            raise self.error(f"unknown {self.kind} '{name}'; choose one of {sorted(self)}{left_out}{plug}")
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



def lazy_exports(package: str, homes: dict[str, Iterable[str]]) -> tuple[Callable[[str], object], list[str]]:
    """A package's PEP 562 ``__getattr__`` and ``__all__`` for names that live in its modules (module -> names):
    each name is imported from ``package.module`` when first asked for, then kept in the package's namespace."""
    where = {name: module for module, names in homes.items() for name in names}

    def __getattr__(name: str) -> object:
        module = where.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{module}"), name)
        setattr(sys.modules[package], name, value)  # later lookups skip this function
        return value

    return __getattr__, sorted(where)
