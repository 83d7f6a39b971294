"""The ``mocap`` command: one entry point, one subcommand per module in ``mocap.commands``.

Each module in ``mocap/commands/`` defines ``register(subparsers)`` which adds its parser and
sets ``func`` to a callable taking the parsed namespace and returning an exit code. The CLI
holds no algorithm: subcommands build an options object and call a library function.
"""
from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys

from . import commands


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("openmocap")
    except PackageNotFoundError:                  # run from a source tree, not installed
        return "(not installed)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mocap", description="Open optical motion capture.")
    parser.add_argument("--version", action="version", version=f"mocap {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        mod = importlib.import_module(f"{commands.__name__}.{info.name}")
        if hasattr(mod, "register"):
            mod.register(sub)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    if os.environ.get("MOCAP_DEBUG"):               # full tracebacks for bug reports
        return int(args.func(args) or 0)
    try:
        return int(args.func(args) or 0)
    except (ValueError, TypeError, OSError) as e:   # OSError: missing, unwritable paths
        print(f"mocap {args.command}: error: {e}", file=sys.stderr)
        return 2
    except (RuntimeError, MemoryError) as e:        # CaptureError (hardware, recordings) too
        what = "out of memory" if isinstance(e, MemoryError) else type(e).__name__
        print(f"mocap {args.command}: {what}: {e} (MOCAP_DEBUG=1 shows the traceback)",
              file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"mocap {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
