"""The entry point: parse, import the command's module, run it; bad input ends in one line (exit 2)."""

from __future__ import annotations

import argparse
import importlib
import pickle
import shlex
import sys
import traceback
import zipfile
from collections.abc import Callable

from coin_app.cli.parser import UsageError, build_parser

USER_ERRORS = (ValueError, ImportError, OSError, EOFError, pickle.UnpicklingError, zipfile.BadZipFile)


def one_line(exc: BaseException) -> str:
    """An exception as one line: its first line, with the type for errors that are not ValueErrors."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    if isinstance(exc, OSError) and exc.filename is not None and str(exc.filename) not in text:
        text += f": {exc.filename}"
    return text if isinstance(exc, ValueError) else f"{type(exc).__name__}: {text}"


def command(run: str) -> Callable[[argparse.Namespace], int]:
    """The function ``"module.cmd_name"`` of ``coin_app.cli``, importing that module (and its machinery) now."""
    module, name = run.rsplit(".", 1)
    return getattr(importlib.import_module(f"coin_app.cli.{module}"), name)


def main(argv: list[str] | None = None) -> int:
    """Entry point; bad input exits with status 2 and a one-line message (``--debug`` anywhere: the traceback too)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv
    argv = [a for a in argv if a != "--debug"]
    try:
        args = build_parser().parse_args(argv)
    except UsageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    args.command_line = shlex.join(["python", "-m", "coin_app", *argv])
    try:
        return int(command(args.run)(args))
    except KeyboardInterrupt as exc:  # Ctrl-C, or a signal a command turned into a stop (its exit_code: 128 + the signal's number)
        print(f"interrupted: {exc}" if str(exc) else "interrupted", file=sys.stderr)
        return int(getattr(exc, "exit_code", 130))
    except Exception as exc:
        if debug:
            traceback.print_exc()
        known = isinstance(exc, USER_ERRORS)
        hint = "" if debug else " (--debug shows the traceback)"
        print(f"error: {one_line(exc)}" + ("" if known else f"; an unexpected error{hint}"), file=sys.stderr)
        return 2 if known else 1
