"""The one command-line entry point, ``wamplan``.

Each command family registers its sub-commands from its module in ``wamplan/cli/`` (``env``, whose module also
registers ``tasks``, ``data``, ``wm``, ``wam``, ``eval``, ``plot``): a function ``register(subparsers)`` decorated
with ``@register_command(name)`` (the ``COMMANDS`` registry below, which lists those modules);
a handler is a function ``(args) -> int``.

``wamplan --help`` and every ``--help`` stay fast (well under a second): a command module imports nothing heavy
at its top (the standard library, ``wamplan.config``) and adds each command with :func:`add_command`, whose
options (generated from config classes that may import torch or ManiSkill) are built only when that command is
chosen. The help of such a command is kept in a cache (``$XDG_CACHE_HOME/wamplan/help``, or
``$WAMPLAN_CACHE_DIR/help``; one file per checkout, refreshed when its sources or the installed plug-ins, the
entry points of the groups ``wamplan.*``, change) once built, so asking again needs none of those imports.

A long command's ``--help`` is its first screen (:func:`first_screen`): the options most runs need and the names of
the groups the others sit in; ``--help-all`` lists them all. Config classes that options are generated from live in
light modules (``train_config``, ``wam/tinywam_config``, ``wam/train_config``), apart from the torch code that uses
them, so that a parser builds without torch.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import sys
from functools import partial
from pathlib import Path
from typing import Any, Callable, Iterator

from wamplan.registry import Registry

COMMANDS = Registry("command", modules=(
    "wamplan.cli.env",
    "wamplan.cli.data",
    "wamplan.cli.wm",
    "wamplan.cli.wam",
    "wamplan.cli.eval",
    "wamplan.cli.plot",
    "wamplan.cli.proxy",
))
register_command = COMMANDS.register  # decorator on a command module's ``register(subparsers)``

HELP_FLAGS = ("-h", "--help")
HELP_ALL = "--help-all"  # a command with a first screen (:func:`first_screen`): every option, in its groups


class Parser(argparse.ArgumentParser):
    """argparse, with sub-commands built on demand (:func:`add_command`) and one short usage line on errors
    (argparse prints the whole usage, ~40 lines for ``eval``, before the line that matters)."""

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.register("action", "parsers", _LazySubParsers)

    def format_help(self, full: bool = False) -> str:  # type: ignore[override]
        """The help; for a command with a first screen (:func:`first_screen`) only its options most runs need and
        the names of the groups the rest sit in, unless ``full`` (``--help-all``)."""
        first = getattr(self, "first_screen", None)
        if full or not first:
            return super().format_help()
        shown = [a for a in self._actions if not a.option_strings or a.required or set(a.option_strings) & first]
        formatter = self._get_formatter()
        formatter.add_usage(None, shown, [], prefix="usage: ")
        formatter.add_text(self.description)
        formatter.start_section("the options most runs need")
        formatter.add_arguments(shown)
        formatter.end_section()
        rest = []
        for group in self._action_groups:
            n = sum(a not in shown and a.help is not argparse.SUPPRESS for a in group._group_actions)
            if n:
                rest.append(f"{'other options' if group.title == 'options' else group.title} ({n})")
        formatter.add_text(f"More options, in groups: {', '.join(rest)}. `{self.prog} {HELP_ALL}` lists them all.")
        return formatter.format_help()

    def error(self, message: str):  # type: ignore[override]
        self.exit(2, f"{self.short_usage()}\n{self.prog}: error: {message}\n")

    def short_usage(self) -> str:
        """``usage: PROG [options] POSITIONALS  (PROG --help lists the options)``."""
        formatter = self._get_formatter()
        formatter.add_usage(None, self._get_positional_actions(), [], prefix="")
        positionals = formatter.format_help().strip()[len(self.prog):].strip()
        return f"usage: {self.prog} [options] {positionals}".rstrip() + f"   (`{self.prog} --help` lists the options)"


class _LazySubParsers(argparse._SubParsersAction):
    """Sub-commands whose options are added by a builder the first time the command is chosen."""

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self._builders: dict[str, tuple[Callable[[argparse.ArgumentParser], None], bool]] = {}

    def add_lazy(self, name: str, build: Callable[[argparse.ArgumentParser], None], cache_help: bool, **kwargs: Any):
        p = self.add_parser(name, **kwargs)
        self._builders[name] = (build, cache_help)
        return p

    def build(self, name: str, asks_help: str | None = None) -> argparse.ArgumentParser:
        """The parser of sub-command ``name``, its options added (once). ``asks_help``: the help flag the command
        line gives this command (``--help`` or ``--help-all``), which a cached copy answers (and exits) without
        building; once built, both helps are cached."""
        sub = self._name_parser_map[name]
        if name in self._builders:
            build, cache_help = self._builders.pop(name)
            asks_help = asks_help if cache_help else None
            if asks_help and _print_cached_help(_help_name(sub.prog, asks_help)):
                sub.exit(0)
            build(sub)
            if asks_help:
                _cache_help({_help_name(sub.prog, "--help"): sub.format_help(),
                             _help_name(sub.prog, HELP_ALL): sub.format_help(full=True)})
        return sub

    def __call__(self, parser, namespace, values, option_string=None):
        name, rest = values[0], values[1:]
        if name not in self._name_parser_map:  # argparse's "invalid choice" error
            return super().__call__(parser, namespace, values, option_string)
        sub = self.build(name, asks_help=_asks_help(rest))
        if self.dest is not argparse.SUPPRESS:
            setattr(namespace, self.dest, name)
        renamed = _named_otherwise(rest, sub)  # before argparse, whose "required" error would hide the reason
        if renamed:
            sub.error(renamed)
        subnamespace, extras = sub.parse_known_args(rest, None)
        for key, value in vars(subnamespace).items():
            setattr(namespace, key, value)
        if extras:  # argparse would pass them up to ``wamplan``'s usage; they belong to this command
            sub.error(f"unrecognized arguments: {' '.join(extras)}{_did_you_mean(extras, sub)}")


# Options that name one thing in different commands (a WAM; a world model; a request size): a command that lacks
# the one given but takes another of its group says so (``--ckpt`` is a WAM in `wam serve`, a world model in `wm eval`).
SYNONYMS = (("--wam", "--upstream", "--ckpt", "--policy"),
            ("--wm-augmented", "--world-model", "--wm", "--ckpt", "--plan-with"),
            ("--max-request-mb", "--max-request-bytes"))


def _usage_flags(parser: argparse.ArgumentParser) -> set[str]:
    """The options ``parser`` takes, read from its usage line (which lists each once, and no prose)."""
    import re

    return set(re.findall(r"(?<![\w-])--[a-z][\w-]*[a-z0-9]", parser.format_usage()))


def _named_otherwise(args: list[str], parser: argparse.ArgumentParser) -> str:
    """For the first option in ``args`` that ``parser`` lacks but names by a synonym (:data:`SYNONYMS`): the error
    line that says so ('unrecognized arguments: --wam; this command names it --upstream'); else ''."""
    known = _usage_flags(parser)
    for arg in args:
        flag = arg.split("=")[0]
        if not flag.startswith("--") or flag in known:
            continue
        names = sorted({s for group in SYNONYMS if flag in group for s in group if s in known})
        if names:
            units = " (in its own units)" if "--max-request-mb" in (flag, *names) else ""
            return f"unrecognized arguments: {flag}; this command names it {' or '.join(names)}{units}"
    return ""


def _did_you_mean(extras: list[str], parser: argparse.ArgumentParser) -> str:
    """'; did you mean --x?' for the first unknown option close to one of ``parser``'s (read from its usage line,
    which lists each option it takes once and no prose)."""
    import difflib

    known = sorted(_usage_flags(parser))
    for arg in extras:
        flag = arg.split("=")[0]
        if flag.startswith("--"):
            close = [c for c in difflib.get_close_matches(flag, known, n=2, cutoff=0.75) if c != flag]
            if close:
                return f"; did you mean {close[0]}?"
    return ""


def add_command(sub: argparse._SubParsersAction, name: str, build: Callable[[argparse.ArgumentParser], None],
                **kwargs: Any) -> argparse.ArgumentParser:
    """Add the command ``name`` (``help=``, ``description=`` ...) whose options ``build(parser)`` adds when it is
    chosen; ``build`` may import anything (config classes, torch). Returns the (still empty) parser."""
    return _add(sub, name, build, True, **kwargs)


def add_group(sub: argparse._SubParsersAction, name: str, build: Callable[[argparse.ArgumentParser], None],
              **kwargs: Any) -> argparse.ArgumentParser:
    """Add the command family ``name`` (e.g. ``wm``) whose ``build(parser)`` adds its sub-commands (with
    :func:`add_command`) when it is chosen; ``build`` itself must stay cheap (its help is not cached). The family
    alone (``wamplan wm``) prints its help."""
    def build_group(parser: argparse.ArgumentParser) -> None:
        parser.set_defaults(func=partial(_print_help, parser))  # a chosen sub-command sets its own func
        build(parser)

    return _add(sub, name, build_group, False, **kwargs)


def _print_help(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    parser.print_help()
    return 2


def _add(sub: argparse._SubParsersAction, name: str, build: Callable[[argparse.ArgumentParser], None],
         cache_help: bool, **kwargs: Any) -> argparse.ArgumentParser:
    if isinstance(sub, _LazySubParsers):
        return sub.add_lazy(name, build, cache_help, **kwargs)
    p = sub.add_parser(name, **kwargs)  # a plain argparse parent: build now
    build(p)
    return p


def _asks_help(args: list[str]) -> str | None:
    """The help flag given to this command (``--help`` for ``-h`` too, or ``--help-all``; not to a sub-command below
    it, and not after ``--``), or None."""
    for a in args:
        if a == "--":
            return None
        if a in HELP_FLAGS:
            return "--help"
        if a == HELP_ALL:
            return HELP_ALL
    return None


def _help_name(prog: str, flag: str) -> str:
    return prog if flag != HELP_ALL else f"{prog} {HELP_ALL}"


class _HelpAll(argparse.Action):
    """``--help-all``: every option of the command, in its groups."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        parser._print_message(parser.format_help(full=True), sys.stdout)
        parser.exit(0)


def first_screen(parser: argparse.ArgumentParser, *flags: str) -> None:
    """Show only ``flags`` (and the positionals, required options and ``-h``) under ``--help``, with the names of the
    groups the other options sit in; ``--help-all`` (added here) lists every option. Call it after adding them."""
    parser.first_screen = {"-h", "--help", HELP_ALL, *flags}  # type: ignore[attr-defined]
    missing = [f for f in flags if f not in parser._option_string_actions]
    if missing:
        raise ValueError(f"{parser.prog}: first_screen names options it lacks: {missing}")
    parser.add_argument(HELP_ALL, action=_HelpAll, help="list every option, in its groups, and exit")


# ---------------------------------------------------------------------------------------------- help cache
def _help_cache() -> tuple[Path, str]:
    """This checkout's help cache, ``$WAMPLAN_CACHE_DIR`` (default ``$XDG_CACHE_HOME/wamplan``)/help/PLACE.json
    (PLACE: a hash of the package's path and the Python version), and the stamp of its sources and of the installed
    plug-ins now (a plug-in's tasks are listed in the help of ``--task``). One file per checkout: checkouts that
    share the cache never touch each other's file."""
    root = Path(os.environ.get("WAMPLAN_CACHE_DIR") or
                Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "wamplan")
    src = Path(__file__).resolve().parents[1]  # the wamplan package
    place = hashlib.sha1(f"{sys.version}\n{src}".encode()).hexdigest()[:16]
    files = [f"{p.relative_to(src)}:{p.stat().st_mtime_ns}:{p.stat().st_size}" for p in sorted(src.rglob("*.py"))]
    files += _plugin_stamp()
    return root / "help" / f"{place}.json", hashlib.sha1("\n".join(files).encode()).hexdigest()[:16]


def _plugin_stamp() -> list[str]:
    """The installed plug-ins: every ``entry_points.txt`` of a distribution on ``sys.path`` (``NAME-VERSION.dist-info``
    or ``.egg-info``) that declares a ``wamplan.*`` group, with its path. Read directly, not through
    importlib.metadata, whose import alone costs more than the rest of a cached ``--help``."""
    found = []
    for entry in sys.path:
        for f in sorted(Path(entry or ".").glob("*.*-info/entry_points.txt")):
            try:
                text = f.read_text()
            except (OSError, UnicodeDecodeError):
                continue  # unreadable: importlib.metadata cannot load it either
            if "[wamplan." in text:
                found.append(f"{f}:{text}")
    return found


def _cached_help(path: Path, stamp: str) -> dict[str, str]:
    """The help texts cached in ``path`` for the sources of ``stamp`` (none when the sources have changed)."""
    try:
        cached = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    texts = cached.get("help") if isinstance(cached, dict) and cached.get("stamp") == stamp else None
    return texts if isinstance(texts, dict) else {}


def _help_key(prog: str) -> str:
    return f"{prog}@{shutil.get_terminal_size().columns}"  # argparse wraps the help to the terminal's width


def _print_cached_help(prog: str) -> bool:
    text = _cached_help(*_help_cache()).get(_help_key(prog))
    if text is None:
        return False
    sys.stdout.write(text)
    return True


def _cache_help(texts: dict[str, str]) -> None:
    """Remember the helps ``texts`` (name -> text) for this version of the sources; a cache that cannot be written
    is skipped."""
    path, stamp = _help_cache()
    cached = _cached_help(path, stamp)  # the help of older sources is dropped
    cached.update({_help_key(name): text for name, text in texts.items()})
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}")
        tmp.write_text(json.dumps({"stamp": stamp, "help": cached}))
        os.replace(tmp, path)
    except (OSError, ValueError):
        pass  # a read-only or damaged cache only costs speed


class _Version(argparse.Action):
    """``--version``: the installed package's version, looked up only when asked."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        from importlib.metadata import PackageNotFoundError, version

        try:
            v = version("wamplan")
        except PackageNotFoundError:
            v = "unknown (not installed; run `pip install -e .`)"
        print(f"wamplan {v} (python {sys.version.split()[0]}, {Path(__file__).resolve().parents[1]})")
        parser.exit(0)


def iter_commands(parser: argparse.ArgumentParser | None = None) -> Iterator[argparse.ArgumentParser]:
    """Every command's parser, its options built (imports everything): for checks over the whole CLI."""
    parser = parser or build_parser()
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name in list(action.choices):
                sub = action.build(name) if isinstance(action, _LazySubParsers) else action.choices[name]
                yield from iter_commands(sub)


def _end_progress_lines() -> None:
    """Close the progress bars a failure left open, so that its one line starts a line of its own."""
    tqdm = sys.modules.get("tqdm")
    for bar in list(getattr(getattr(tqdm, "tqdm", None), "_instances", ())):
        bar.close()


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="wamplan", description="wamplan: world-model feedback planning for world action models "
                                                "(WAMs). `wamplan COMMAND --help` lists a command's options.")
    parser.add_argument("--version", action=_Version, help="print the version of wamplan and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for register in COMMANDS.values():
        register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    from wamplan.errors import UserError

    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except UserError as e:
        _end_progress_lines()
        print(f"wamplan: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("wamplan: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
