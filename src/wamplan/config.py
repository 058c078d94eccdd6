"""Config helpers: frozen dataclasses, validated in ``__post_init__``, that round-trip through JSON
and double as argparse options (a field's ``help`` metadata is its ``--help`` text).

    @dataclass(frozen=True)
    class TrainConfig:
        lr: float = field(3e-4, "peak learning rate")
        def __post_init__(self):
            require(self.lr > 0, f"lr must be > 0, got {self.lr}; pass a positive --lr")
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import numbers
import os
import re
import types
import typing
from pathlib import Path
from typing import Any, Iterable, TypeVar

from wamplan.errors import UserError

T = TypeVar("T")


class ConfigError(UserError, ValueError):
    """A config value is wrong; the message says which and how to fix it."""


def field(default: Any = dataclasses.MISSING, help: str = "", cli: bool = True, choices: Any = None,
          listed: Any = None, **kw: Any) -> Any:
    """A dataclass field with a help string (used for ``--help``). Mutable defaults: pass a tuple, or
    ``default_factory=``. ``cli=False`` keeps the field out of :func:`add_arguments` (set it otherwise).
    ``choices``: the values its option accepts (argparse refuses others and lists them in ``--help``), or a
    function returning them (e.g. a registry's names, read when the option is built). ``listed``: the same, but
    only listed in ``--help``; the config's ``__post_init__`` checks the value (a registry that plug-ins fill,
    whose error says which plug-in was left out)."""
    return dataclasses.field(default=default, metadata={"help": help, "cli": cli, "choices": choices,
                                                        "listed": listed}, **kw)


def choices_metavar(choices: Iterable[Any]) -> str:
    """``{a,b,c}``, as argparse shows an option's choices."""
    return "{" + ",".join(str(c) for c in choices if c != "") + "}"


def with_default(cls: type, name: str, default: Any) -> Any:
    """``cls``'s field ``name`` with another default, for a subclass that redeclares it: the help stays the
    base's and the field keeps its place in the base's order (in ``--help`` and in saved configs)."""
    return dataclasses.field(default=default, metadata=cls.__dataclass_fields__[name].metadata)


def require(cond: bool, message: str) -> None:
    """Raise ConfigError(message) unless cond holds."""
    if not cond:
        raise ConfigError(message)


def check_numbers(cfg: Any, infinite: tuple[str, ...] = ()) -> None:
    """Refuse, in one ConfigError naming the field, a value of a number field (``int`` or ``float``, optional or a
    tuple of them) of the dataclass ``cfg`` that is not a finite number: a string, ``nan`` or ``inf``, and a value of
    a text field (``str``, optional or a tuple of them) that is not a str or a path (``infinite``
    names the fields where ±inf means something, e.g. a gate every cost passes). Configs call it first in
    ``__post_init__``; their own checks (ranges, relations) follow."""
    try:
        hints = _hints(type(cfg))
    except NameError:  # an annotation only a type checker resolves (a plugin's): its fields go unchecked here
        return
    for f in dataclasses.fields(cfg):
        st = _scalar_type(hints[f.name])
        if st is str and _only(hints[f.name], str):  # text: a str (or a path), never a number, e.g. url=8777
            value = getattr(cfg, f.name)
            for v in value if isinstance(value, (tuple, list)) else (value,):
                require(v is None or isinstance(v, (str, os.PathLike)),
                        f"{type(cfg).__name__}.{f.name} must be text (a str), got {type(v).__name__} {v!r}")
            continue
        if st not in (int, float):
            continue
        value = getattr(cfg, f.name)
        many = isinstance(value, (tuple, list)) or getattr(value, "ndim", 0) > 0  # a sequence, array or tensor
        for v in value if many else (value,):
            if v is None:
                continue
            v = v.item() if getattr(v, "ndim", None) == 0 and hasattr(v, "item") else v  # 0-d array or tensor
            ok = (isinstance(v, numbers.Real) and not isinstance(v, bool)  # numpy's numbers too
                  and (math.isfinite(v) or (f.name in infinite and not math.isnan(v))))
            require(ok or (st is int and isinstance(v, bool)),
                    f"{type(cfg).__name__}.{f.name} must be {'finite numbers' if many else 'a finite number'}, "
                    f"got {v!r}{f' in {value!r}' if many else ''}")


def to_dict(cfg: Any) -> dict[str, Any]:
    """A JSON-ready dict of a (possibly nested) config dataclass; tuples become lists."""
    out = {}
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v):
            v = to_dict(v)
        elif isinstance(v, tuple):
            v = list(v)
        out[f.name] = v
    return out


def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def from_dict(cls: type[T], data: dict[str, Any]) -> T:
    """Build ``cls`` from a dict, rejecting unknown keys (a typo must not pass silently)."""
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    require(not unknown, f"{cls.__name__}: unknown keys {unknown}; known keys are {sorted(names)}")
    hints = _hints(cls)
    kwargs = {}
    for k, v in data.items():
        t = hints[k]
        if dataclasses.is_dataclass(t) and isinstance(v, dict):
            v = from_dict(t, v)
        elif isinstance(v, list):
            v = tuple(v)
        kwargs[k] = v
    return cls(**kwargs)


def int_list(spec: str, flag: str, example: str = "500-503 or 500,510") -> list[int]:
    """The integers of a command-line list such as ``500-503,510`` (ranges inclusive), in the order given.

    A malformed, backward or empty ``spec`` raises :class:`UserError` naming ``flag`` and the expected form
    (``example``)."""
    out: list[int] = []
    for part in (p.strip() for p in spec.split(",") if p.strip()):
        lo, _, hi = part.partition("-")
        try:
            first, last = int(lo), int(hi or lo)
        except ValueError:
            raise UserError(f"{flag} '{spec}' is not a list like {example}") from None
        if last < first:
            raise UserError(f"{flag} '{spec}': the range {part} runs backwards; write {last}-{first}")
        out.extend(range(first, last + 1))
    if not out:
        raise UserError(f"{flag} needs at least one number, e.g. {example.split(' or ')[0]}")
    return out


def save_json(cfg: Any, path: str | Path) -> None:
    Path(path).write_text(json.dumps(to_dict(cfg), indent=2) + "\n")


def load_json(cls: type[T], path: str | Path) -> T:
    return from_dict(cls, json.loads(Path(path).read_text()))


def _only(t: Any, kind: type) -> bool:
    """Whether the annotation ``t`` admits ``kind`` alone (or None, or a tuple of it): ``str``, ``str | None`` and
    ``tuple[str, ...]`` do, ``str | int`` does not."""
    origin = typing.get_origin(t)
    if origin in (typing.Union, types.UnionType):
        return all(a is type(None) or _only(a, kind) for a in typing.get_args(t))
    if origin is tuple:
        return all(a is Ellipsis or _only(a, kind) for a in typing.get_args(t))
    return t is kind


def _scalar_type(t: Any) -> Any:
    """The argparse type of an annotation: unwrap Optional[X] and tuple[X, ...]."""
    origin = typing.get_origin(t)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(t) if a is not type(None)]
        return _scalar_type(args[0])
    if origin is tuple:
        return _scalar_type(typing.get_args(t)[0])
    return t


def add_field_argument(parser: Any, flag: str, dest: str, f: dataclasses.Field, t: Any, help_: str = "",
                       default_text: str | None = None) -> None:
    """Add ``flag`` for the dataclass field ``f`` (type hint ``t``) to ``parser`` (or an argument group):
    its default is None, meaning "keep the config's default". ``default_text``: what the help says the default
    is, when it is not the field's own (e.g. a preset's)."""
    if not help_:
        help_ = f.metadata.get("help", "")
        default = f.default if f.default is not dataclasses.MISSING else None
        if default_text is None and ("(default" in help_ or default in ("", None, ())):
            default_text = ""  # the help says it already, or there is nothing to show
        default_text = f"default: {default}" if default_text is None else default_text
        help_ = f"{help_} ({default_text})" if help_ and default_text else help_ or f"({default_text})"
    st = _scalar_type(t)
    metavar = flag.lstrip("-").replace("-", "_").upper()
    choices, listed = (c() if callable(c) else c for c in (f.metadata.get("choices"), f.metadata.get("listed")))
    choices = tuple(choices) if choices is not None else None
    if choices is not None or listed is not None:
        metavar = choices_metavar(choices if choices is not None else sorted(listed))
    if st is bool:
        parser.add_argument(flag, dest=dest, default=None, action=argparse.BooleanOptionalAction, help=help_)
    elif tuple in (typing.get_origin(t), *(typing.get_origin(a) for a in typing.get_args(t))):  # tuple[...] | None too
        parser.add_argument(flag, dest=dest, default=None, nargs="+", type=st, metavar=metavar, help=help_,
                            choices=choices)
    else:
        parser.add_argument(flag, dest=dest, default=None, type=st if st in (int, float, str) else str,
                            metavar=metavar, help=help_, choices=choices)


def add_arguments(parser: Any, cls: type, prefix: str = "", presets: dict[str, Any] | None = None) -> None:
    """Add one ``--name`` option per scalar field of ``cls`` (default None = keep the config default);
    nested configs and fields declared with ``cli=False`` are skipped. ``presets`` ({name: instance of
    cls}): the defaults come from the chosen preset, and the help shows each preset's value."""
    hints = _hints(cls)
    for f in dataclasses.fields(cls):
        t = hints[f.name]
        if dataclasses.is_dataclass(t) or not f.metadata.get("cli", True):
            continue
        add_field_argument(parser, "--" + (prefix + f.name).replace("_", "-"), prefix + f.name, f, t,
                           default_text=preset_default_text(f.name, presets))


def preset_default_text(name: str, presets: dict[str, Any] | None) -> str | None:
    """'default: the preset's, mini 4, paper 24' (or 'default: 1.0' when all agree; '' when all agree on nothing, an
    empty string, None or ()) for field ``name`` of the configs in ``presets``; None without presets."""
    if not presets:
        return None
    values = {label: getattr(c, name) for label, c in presets.items()}
    if len(set(map(str, values.values()))) == 1:
        value = next(iter(values.values()))
        return "" if value in ("", None, ()) else f"default: {value}"
    return "default: the preset's, " + ", ".join(f"{label} {v}" for label, v in values.items())


def from_args(cls: type[T], args: argparse.Namespace, base: T | None = None, prefix: str = "") -> T:
    """Overlay the options the user passed (not None) onto ``base`` (or the defaults). ``base`` may be of
    another config class than ``cls`` (the one the options were generated from): an option passed for a
    field ``base`` lacks is refused."""
    base = base if base is not None else cls()
    changes = {}
    for f in dataclasses.fields(cls):
        v = getattr(args, prefix + f.name, None) if f.metadata.get("cli", True) else None
        if v is not None:
            changes[f.name] = tuple(v) if isinstance(v, list) else v
    extra = sorted(set(changes) - {f.name for f in dataclasses.fields(base)})
    require(not extra, f"{', '.join('--' + (prefix + k).replace('_', '-') for k in extra)} does not apply to "
                       f"{type(base).__name__}; drop it")
    try:
        return dataclasses.replace(base, **changes)
    except ConfigError as e:  # the config names its fields; on the command line they are options
        flags = {f.name: "--" + (prefix + f.name).replace("_", "-") for f in dataclasses.fields(cls)
                 if f.metadata.get("cli", True)}
        raise ConfigError(as_options(str(e), type(base).__name__, flags)) from None


def as_options(text: str, cls_name: str, flags: dict[str, str]) -> str:
    """``text``, a config's error, with its field names written as the options that set them (``flags``: field ->
    option): ``Cls.field``, a snake_case field anywhere, a field that opens the message (its subject) or is quoted
    with its value (``epochs=10``); "or None" (a field's unset value) reads "or unset"."""
    for name in sorted(flags, key=len, reverse=True):
        text = text.replace(f"{cls_name}.{name}", flags[name])
        pattern = rf"(?<![\w.-]){name}(?![\w-])" if "_" in name else rf"^{name}(?![\w-])|(?<![\w.-]){name}(?==)"
        text = re.sub(pattern, flags[name], text)
    return text.replace(" or None", " or unset")


# The last commit that plans in an ensemble of world models (several checkpoints joined by + or commas, with
# --disagreement-weight), named where such input is refused (their record: lab/README.md).
ENSEMBLES_LAST = "5eecf06"


def joined_checkpoints(spec: str) -> list[str]:
    """The world-model checkpoint directories ``spec`` joins with ``+`` or commas (``A+B``, ``A,B``: an ensemble,
    which wamplan no longer plans in), or [] where it names one path. A path may hold a ``+`` or a comma: one that
    exists is one checkpoint (``runs/exp+v2/wm``), and so is a spec whose pieces are not all checkpoint directories
    (the caller's missing-path check then names it whole)."""
    if not spec or Path(spec).exists():
        return []
    pieces = [m for part in spec.split(",") for m in ([part] if Path(part).exists() else part.split("+"))]
    joined = len(pieces) > 1 and all(p and (Path(p) / "config.json").is_file() for p in pieces)
    return pieces if joined else []


def one_checkpoint(spec: str, flag: str) -> str:
    """``spec``, one world-model checkpoint path; one line naming ``flag`` and the fix where it joins several
    (:func:`joined_checkpoints`)."""
    pieces = joined_checkpoints(spec)
    if pieces:
        raise UserError(f"{flag} {spec} joins {len(pieces)} world models into an ensemble, which wamplan no longer "
                        f"plans in (it measured no gain; the last commit that has it is {ENSEMBLES_LAST}); pass one "
                        f"checkpoint, e.g. {flag} {pieces[0]}")
    return spec


class Once(argparse.Action):
    """An option that may be given once: a second ``--opt`` is refused (argparse keeps the last silently), e.g. two
    ``--encoder-kwargs`` of which only the last would be used. ``hint`` (class attribute): what to do instead."""

    hint = ""

    def __call__(self, parser, namespace, values, option_string=None):
        if getattr(namespace, self.dest, None) not in (None, self.default):
            parser.error(f"{option_string} given twice; give it once" + (self.hint and f" ({self.hint})"))
        setattr(namespace, self.dest, values)
