"""`phd` command line: one module per command group, each with `register(subparsers)`."""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import warnings

# Idle OpenMP threads sleep instead of spinning: with spinning, torch on a busy or shared
# 2-core machine ran 3-25x slower (docs/gaussians.md). Must be set before torch loads.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from phd_core.allocator import keep_freed_memory
from phd_core.errors import InputError, ModelNote, ModelWarning

# Each module defines register(subparsers) and sets `func` on its parsers.
COMMAND_MODULES = ("capture", "train", "render", "serve", "loop", "demo", "uq", "candidates", "view")


def build_parser() -> argparse.ArgumentParser:
    from phd_core.renderers import FAMILIES

    parser = argparse.ArgumentParser(prog="phd", description="PH-Dropout: post hoc epistemic uncertainty "
                                     f"for trained models ({', '.join(FAMILIES)}).")
    subparsers = parser.add_subparsers(dest="command", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(f"{__name__}.{name}").register(subparsers)
    _literal_help(parser)
    return parser


def _literal_help(parser: argparse.ArgumentParser) -> None:
    """Every option's help as plain text: argparse %-formats it, and text read from a registry
    ("the top 10 % of pixels") would break --help. No help here uses %(default)s."""
    for action in parser._actions:
        if action.help:
            action.help = action.help.replace("%", "%%")
        if isinstance(action, argparse._SubParsersAction):
            for command in action.choices.values():
                _literal_help(command)


def main(argv: list[str] | None = None) -> int:
    keep_freed_memory()     # malloc keeps freed memory for the renderer's large temporaries (phd_core.allocator)
    args = build_parser().parse_args(argv)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", ModelNote)
            warnings.simplefilter("always", ModelWarning)
            warnings.showwarning = _model_messages(args.command, warnings.showwarning)
            return int(args.func(args) or 0)
    except InputError as exc:
        print(f"phd {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


def _model_messages(command: str, default):
    """A showwarning that prints the model loaders' notes and warnings as `phd <command>: note: ...`."""
    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, (ModelNote, ModelWarning)):
            kind = "note" if issubclass(category, ModelNote) else "warning"
            print(f"phd {command}: {kind}: {message}", file=sys.stderr)
        else:
            default(message, category, filename, lineno, file, line)
    return show
