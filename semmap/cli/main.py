"""The `semmap` command: run the pipeline, fetch models, detect, evaluate, view and query maps.

Each module of this package that defines `register(subparsers)` adds its commands (optionally `ORDER`, lower
first in the help); this file only finds them. Command modules keep heavy imports inside their handlers, so
`semmap --help` and a refused `semmap run` stay quick.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import pkgutil
import sys

import semmap.cli
from semmap.core.logs import configure_logging


def command_modules() -> list:
    """Every module of semmap.cli that registers commands, in help order."""
    modules = []
    for info in pkgutil.iter_modules(semmap.cli.__path__):
        if info.name in ("main", "__main__"):
            continue
        module = importlib.import_module(f"semmap.cli.{info.name}")
        if callable(getattr(module, "register", None)):
            modules.append(module)
    return sorted(modules, key=lambda m: (getattr(m, "ORDER", 100), m.__name__))


def package_version() -> str:
    """The installed distribution's version (pyproject.toml's where semmap runs from a checkout)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("semmap")
    except PackageNotFoundError:
        return "(not installed)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="semmap", description=__doc__.split("\n\n")[0])
    parser.add_argument("--version", action="version", version=f"semmap {package_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in command_modules():
        module.register(sub)
    return parser


def one_line(exc: BaseException) -> str:
    """An exception as one line: an OSError as its reason and file, anything else as its first line."""
    if isinstance(exc, OSError) and exc.strerror:
        return f"{exc.strerror}: {exc.filename}" if exc.filename else exc.strerror
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    ros_args = argv[argv.index("--ros-args") :] if argv[:1] == ["ros2"] and "--ros-args" in argv else []
    args, extra = parser.parse_known_args(argv[: len(argv) - len(ros_args)])
    if extra and not getattr(args, "passthrough", False):  # (a command that parses its own options takes them)
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    args.extra, args.ros_args = extra, ros_args
    configure_logging(getattr(args, "verbose", False), "semmap")
    logging.getLogger("semmap.run").setLevel(logging.INFO)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # `semmap query ... | head`: the reader left; say nothing more
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # Python flushes stdout at exit: into /dev/null, not a traceback
        return 141
    except Exception as exc:  # a user sees one line, never a traceback (-v: the traceback too)
        logging.getLogger("semmap").debug("%s failed", args.command, exc_info=True)
        print(f"error: semmap {args.command}: {one_line(exc)}", file=sys.stderr)
        return 1
    finally:
        if argv is None:  # a process of its own: Zenoh's threads must not keep it alive past its end
            from semmap.runtime.transport.service import exit_backstop

            exit_backstop()


if __name__ == "__main__":
    sys.exit(main())
