"""Entry point of the ``rough-map`` command.

Command modules import the library's heavy stages (``rough_map.workflow``,
``rough_map.features``, ``rough_map.classify`` ... which pull in scikit-learn, matplotlib,
OpenCV) inside their ``run`` functions, not at the top: building the parser imports every
command module, and ``rough-map --help`` should not wait for them. This is the one reason
the CLI defers imports of rough_map modules; private helper modules (``_common``,
``_traverse_features``) are not commands and are not imported by the parser.
"""

from __future__ import annotations

import argparse
import atexit
import importlib
import logging
import os
import pkgutil
import re
import shlex
import signal
import sys
import warnings

import rough_map.cli
from rough_map import __version__
from rough_map.cli._common import CommandParser, Parser, add_verbosity_args, error_line
from rough_map.errors import RoughMapError

# Every public module of this package that defines ``register`` is a command.
_NOT_COMMANDS = {"main"}


def _command_modules() -> list[str]:
    names = sorted(m.name for m in pkgutil.iter_modules(rough_map.cli.__path__))
    return [f"rough_map.cli.{n}" for n in names if n not in _NOT_COMMANDS and n[0] != "_"]


log = logging.getLogger("rough_map")


def build_parser() -> argparse.ArgumentParser:
    """The ``rough-map`` parser: one sub-parser (a :class:`CommandParser`) per command."""
    parser = Parser(
        prog="rough-map",
        description="Terrain roughness, terrain class and semantic maps from point clouds.",
    )
    parser.add_argument("--version", action="version", version=f"rough-map {__version__}")
    add_verbosity_args(parser)
    # Every command's parser also takes -v/-q (with SUPPRESS defaults), so that both
    # `rough-map -q map ...` and `rough-map map ... -q` work.
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=CommandParser)
    for name in _command_modules():
        module = importlib.import_module(name)
        if hasattr(module, "register"):
            module.register(sub)
    return parser


def _configure_logging(verbose: int, quiet: bool) -> None:
    level = (
        logging.ERROR
        if quiet
        else (logging.DEBUG if verbose > 1 else logging.INFO if verbose == 1 else logging.WARNING)
    )
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger("rough_map")
    root.handlers[:] = [handler]
    root.setLevel(level)
    root.propagate = False


def entry() -> None:
    """The ``rough-map`` command: :func:`main`, and the process's exit with its status.

    After a Ctrl-C the process ends without the interpreter's own shut-down: the exit
    handlers run (loky's workers stop, their semaphores are removed, temporary files go),
    then :func:`os._exit`. A library's thread interrupted mid-way could otherwise hang that
    shut-down or call into an interpreter already finalising (a fatal error, exit -6)."""
    code = main()
    if code == 130:
        _exit_now(code)
    sys.exit(code)


def _exit_now(code: int) -> None:
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    try:
        atexit._run_exitfuncs()
    except BaseException:  # a second Ctrl-C, or a handler that failed: leave all the same
        pass
    os._exit(code)


def main(argv: list[str] | None = None) -> int:
    """Run ``rough-map`` with ``argv`` (default: ``sys.argv[1:]``); returns the exit status.

    A bad argument returns 2 after one line on stderr, as an error of a command does;
    ``--help`` and ``--version`` return 0; a Ctrl-C at any moment, 130 after one line.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        # blocked since rough_map.cli was imported (see there): the main thread takes it
        # again, and a Ctrl-C that came during the imports is taken now
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
        return _main(argv)
    except KeyboardInterrupt:  # while the parser is built, or the arguments read
        print("rough-map: interrupted", file=sys.stderr)
        return 130


def _main(argv: list[str]) -> int:
    try:
        parser = build_parser()
    except Exception as exc:  # a broken install: still one line, no traceback
        if _interrupted(exc):
            raise KeyboardInterrupt from exc
        print(failure_line("", exc), file=sys.stderr)
        return 2
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse's exit after --help, --version or a bad argument
        return exc.code if isinstance(exc.code, int) else 2
    except Exception as exc:  # an argument type that failed otherwise: still one line
        print(failure_line("", exc), file=sys.stderr)
        return 2
    if args.command is None:
        print(
            "rough-map: error: a command is required (`rough-map --help` lists them)",
            file=sys.stderr,
        )
        return 2
    # Configure the 'rough_map' logger for this run only, and put it back afterwards, so
    # that calling main() from Python (tests, notebooks) leaves logging as it was.
    logger = logging.getLogger("rough_map")
    saved = logger.handlers[:], logger.level, logger.propagate
    _configure_logging(args.verbose, args.quiet)
    args.progress = not args.quiet and sys.stderr.isatty()
    # The command line as typed (for records such as a model card), whatever the order
    # of the options around the command name.
    args.command_line = "rough-map " + shlex.join(str(a) for a in argv)
    try:
        with warnings.catch_warnings():
            # rough_map's warnings (an all-nodata map...) read as log lines, not as the
            # source line that raised them; -q silences them with the other warnings.
            warnings.showwarning = _log_warning
            return _run(args)
    finally:
        logger.handlers[:], logger.level, logger.propagate = saved


def _log_warning(message, category, filename, lineno, file=None, line=None) -> None:
    # numpy's floating-point RuntimeWarnings (overflow on absurd coordinates...) say nothing
    # to a user that the result or the error does not: they are debug lines (-vv).
    level = logging.DEBUG if issubclass(category, RuntimeWarning) else logging.WARNING
    logging.getLogger("rough_map.cli").log(level, "%s: %s", category.__name__, message)


def _run(args: argparse.Namespace) -> int:
    """Run the command; every failure is one line on stderr and exit status 2."""
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("rough-map: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # The reader of stdout went away (e.g. `| head`): stop quietly.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141
    except Exception as exc:  # the last line of defence: one line
        if _interrupted(exc):
            print("rough-map: interrupted", file=sys.stderr)
            return 130
        print(failure_line(args.command, exc), file=sys.stderr, flush=True)
        return 2


def _interrupted(exc: BaseException) -> bool:
    """Whether ``exc`` stands for a Ctrl-C: a pybind11 extension (open3d, cv2, scipy's
    pocketfft...) that a Ctrl-C interrupts while it is imported raises
    ``ImportError('initialization failed')`` from the ``KeyboardInterrupt``."""
    seen: set[int] = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, KeyboardInterrupt):
            return True
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    return False


def failure_line(command: str, exc: BaseException) -> str:
    """The one line ``rough-map CMD: error: ...`` for an exception a command raised.

    A :class:`RoughMapError` (also one re-raised from a joblib worker), a bad value of an
    option found late (``argparse.ArgumentTypeError``), an ``OSError`` (named by its file),
    a ``MemoryError`` and a killed worker process are errors of the input or the machine;
    anything else is an internal error, whose traceback ``-vv`` logs.
    """
    prog = f"rough-map {command}".rstrip()
    if isinstance(exc, (RoughMapError, argparse.ArgumentTypeError, argparse.ArgumentError)):
        log.debug("error", exc_info=exc)
        return error_line(prog, _text(exc) or type(exc).__name__)
    if isinstance(exc, MemoryError):
        log.debug("out of memory", exc_info=exc)
        detail = _text(exc)
        return error_line(
            prog,
            f"out of memory while running {command}"
            + (f" ({detail})" if detail else "")
            + "; try a smaller input or fewer --jobs",
        )
    if isinstance(exc, OSError) and not _is_process_pool_error(exc):
        log.debug("system error", exc_info=exc)
        return error_line(prog, _os_message(exc))
    if _is_process_pool_error(exc):
        log.debug("worker process failed", exc_info=exc)
        text = _text(exc)
        codes = re.search(r"exit codes of the workers are (\{[^}]*\})", text)
        if codes or type(exc).__name__ == "TerminatedWorkerError":
            what = f" (exit codes {codes.group(1)})" if codes else ""
            reason = f"a worker process died{what}: out of memory or a crash in a library"
        else:  # e.g. a result that could not be sent back
            reason = f"a worker process failed ({text.splitlines()[0] if text else 'no reason'})"
        return error_line(prog, reason + "; rerun with -j 1 to see the error")
    if log.isEnabledFor(logging.DEBUG):
        log.error("internal error", exc_info=exc)
    return error_line(
        prog,
        f"{type(exc).__name__}: {_text(exc)}",
        kind="internal error",
        suffix=" (please report; rerun with -vv for the traceback)",
    )


def _text(exc: BaseException) -> str:
    try:
        return str(exc)
    except Exception:  # an exception whose str() fails
        return repr(exc.args)[:200]


def _os_message(exc: OSError) -> str:
    """``FILE: reason`` (``FILE -> FILE2: reason`` for a rename), or the message as is."""
    reason = exc.strerror or _text(exc) or type(exc).__name__
    names = [
        os.fsdecode(n) if isinstance(n, bytes) else str(n)
        for n in (exc.filename, exc.filename2)
        if n is not None
    ]
    return f"{' -> '.join(names)}: {reason}" if names else reason


def _is_process_pool_error(exc: BaseException) -> bool:
    """A process pool broke: a worker was killed (joblib/loky's ``TerminatedWorkerError``),
    or a result could not be sent back."""
    from concurrent.futures.process import BrokenProcessPool

    return isinstance(exc, BrokenProcessPool) or type(exc).__name__ == "TerminatedWorkerError"


if __name__ == "__main__":
    sys.exit(main())
