"""Command-line options for every registered planner, generated from the planners' config classes.

A planner registered with ``@register_planner`` (its ``config_cls`` a frozen config dataclass) gets its
options on any command that calls :func:`add_planner_arguments`, with no edit to that command:

* a field is offered as ``--<field>`` (e.g. ``--num-candidates``, ``--temperature``), shared by every
  planner whose config has a field of that name and type; the help says which planners take it;
* a field whose name clashes (another type in another planner, or a flag the command already has) is
  offered per planner as ``--<planner>-<field>`` instead.

:func:`planner_config_from_args` builds the chosen planner's config from the options given and refuses an
option the chosen planner does not have, naming the planners that do.
"""

from __future__ import annotations

import argparse
import dataclasses
import typing
from collections import defaultdict
from typing import Any

from wamplan.config import ConfigError, add_field_argument, as_options
from wamplan.errors import UserError
from wamplan.planning.configs import DEFAULT_PLANNER, PLANNER_CONFIGS

_DEST = "planner_opt__"  # dest prefix: planner_opt__<planner or empty>__<field>


def add_planner_arguments(parser: argparse.ArgumentParser, default: str = DEFAULT_PLANNER) -> None:
    """Add ``--planner`` and one option per planner config field (see the module docstring)."""
    names = sorted(PLANNER_CONFIGS)
    parser.add_argument("--planner", default=None, choices=names,
                        help=f"planner by registry name (default: {default}); wamplan: MPPI at wamplan's default settings "
                             f"(planning/configs.py); cem: the paper's CEM")
    parser.set_defaults(planner_default=default)
    group = parser.add_argument_group(
        "planner options", "settings of the planner's config; each applies to the planners listed in brackets")
    fields: dict[str, list[tuple[str, dataclasses.Field, Any]]] = defaultdict(list)
    for name in names:
        cls = PLANNER_CONFIGS[name]
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            fields[f.name].append((name, f, hints[f.name]))
    taken = set(parser._option_string_actions)  # the command's own flags win
    for fname, entries in fields.items():
        flag = "--" + fname.replace("_", "-")
        if len({str(t) for _, _, t in entries}) == 1 and flag not in taken:
            _add(group, flag, f"{_DEST}__{fname}", entries)
        else:
            for name, f, t in entries:
                _add(group, f"--{name}-{fname}".replace("_", "-"), f"{_DEST}{name}__{fname}", [(name, f, t)])


def _add(group: Any, flag: str, dest: str, entries: list[tuple[str, dataclasses.Field, Any]]) -> None:
    _, f, t = entries[0]
    defaults = {name: (g.default if g.default is not dataclasses.MISSING else None) for name, g, _ in entries}
    shown = next(iter(defaults.values())) if len(set(map(repr, defaults.values()))) == 1 else \
        ", ".join(f"{k}: {v}" for k, v in defaults.items())
    help_ = f"{f.metadata.get('help', '')} (default: {shown}) [{', '.join(defaults)}]"
    add_field_argument(group, flag, dest, f, t, help_=help_.replace("%", "%%"))


def planner_config_from_args(args: argparse.Namespace) -> tuple[str, Any]:
    """``(planner name, its config)`` from parsed options; an option of another planner is an error."""
    name = getattr(args, "planner", None) or getattr(args, "planner_default", DEFAULT_PLANNER)
    cls = PLANNER_CONFIGS.lookup(name)
    known = {f.name for f in dataclasses.fields(cls)}
    changes, flags = {}, {}  # field -> value given; field -> the option that sets it for this planner
    for dest, v in vars(args).items():
        if not dest.startswith(_DEST):
            continue
        owner, fname = dest[len(_DEST):].split("__", 1)
        flag = "--" + (f"{owner}-{fname}" if owner else fname).replace("_", "-")
        if owner in ("", name) and fname in known:
            flags[fname] = flag
        if v is None:
            continue
        if (owner and owner != name) or fname not in known:
            takers = sorted(p for p, c in PLANNER_CONFIGS.items() if fname in {g.name for g in dataclasses.fields(c)})
            raise UserError(f"{flag} is an option of planner(s) {takers}, not of '{name}'; "
                            f"drop it or pass --planner {takers[0] if takers else '...'}")
        changes[fname] = tuple(v) if isinstance(v, list) else v
    try:
        return name, cls(**changes)
    except ConfigError as e:  # the config names its fields; here they are options
        raise ConfigError(as_options(str(e), cls.__name__, flags)) from None
