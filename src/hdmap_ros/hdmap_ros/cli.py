"""The ``hdmap`` command line: one sub-command per module in ``hdmap_ros.commands``.

Each command module exposes ``NAME`` (the sub-command), ``HELP`` (one line), ``add_arguments(parser)``
and ``run(args) -> int`` (the exit code). A command that is not importable (e.g. an optional
dependency missing) is listed with the reason instead of breaking the whole CLI.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from hdmap_core.errors import HdmapError

__all__ = ["main", "COMMAND_MODULES"]

# Order is the order of `hdmap --help`.
COMMAND_MODULES = ("simulate", "bag2map", "export", "evaluate", "bench", "run")


def _load_commands() -> tuple[dict, dict]:
    loaded, broken = {}, {}
    for name in COMMAND_MODULES:
        try:
            loaded[name] = importlib.import_module(f"hdmap_ros.commands.{name}")
        except ModuleNotFoundError as err:
            if err.name == f"hdmap_ros.commands.{name}":
                continue  # not written yet
            broken[name] = err
    return loaded, broken


def build_parser() -> argparse.ArgumentParser:
    loaded, broken = _load_commands()
    parser = argparse.ArgumentParser(
        prog="hdmap",
        description="Lane-level HD maps from noisy vehicle-fleet data (Immel et al. 2023, with EM).",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in loaded.values():
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=mod.HELP)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    for name, err in broken.items():
        p = sub.add_parser(name, help=f"(unavailable: {err})")
        p.set_defaults(_run=lambda _a, e=err: _unavailable(e))
    return parser


def _unavailable(err: Exception) -> int:
    print(f"hdmap: this command is unavailable here: {err}", file=sys.stderr)
    return 2


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except HdmapError as err:
        print(f"hdmap {args.command}: error: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"hdmap {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
