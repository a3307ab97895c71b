"""The ``octofactor`` command line.

Each subcommand lives in its own ``pipelines/*_cmd.py`` module with a
``register(add_command)`` function. Those modules import nothing heavy at module
level (no open3d, cv2, numba, gtsam): heavy imports go inside the command's
``run`` function so that ``octofactor --help`` stays fast.
"""
from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Callable

# Subcommand modules, in the order they appear in --help.
COMMAND_MODULES = (
    "pipelines.graph_cmd",
    "pipelines.map_cmd",
    "pipelines.vp_cmd",
    "pipelines.simulate_corridor_cmd",
    "pipelines.simulate_room_cmd",
    "pipelines.vpslam_cmd",
    "pipelines.register_cmd",
    "pipelines.eval_cmd",
    "pipelines.plugins_cmd",
    "pipelines.demo_cmd",
)

# Commands that group sub-subcommands: `octofactor graph info`, `octofactor simulate room`, ...
GROUPS = {
    "graph": "pose graphs: info, convert, optimize (.graph / .g2o / TUM / KITTI)",
    "octree": "octree files: info, convert, export (.bt / .ot)",
    "simulate": "synthetic data sets: corridor (RGB-D sequence), room (semantic clouds)",
}

AddCommand = Callable[..., argparse.ArgumentParser]


class _Parser(argparse.ArgumentParser):
    """argparse with one-line usage errors (``--help`` still shows the usage)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())} (see --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="octofactor",
        description="Probabilistic estimation on factor graphs for robot perception.",
    )
    parser.add_argument("--version", action="version", version="octofactor 0.1.0")
    top = parser.add_subparsers(dest="command", metavar="COMMAND")
    groups: dict[str, argparse._SubParsersAction] = {}

    def add_command(name: str, help: str, group: str | None = None) -> argparse.ArgumentParser:
        if group is None:
            command = top.add_parser(name, help=help, description=help)
        else:
            if group not in groups:
                group_parser = top.add_parser(group, help=GROUPS[group],
                                              description=GROUPS[group])
                groups[group] = group_parser.add_subparsers(dest="subcommand",
                                                            metavar="SUBCOMMAND")
                group_parser.set_defaults(func=lambda args, p=group_parser: _usage(p))
            command = groups[group].add_parser(name, help=help, description=help)
        # one convention for every command (pipelines/cli_common.py)
        command.add_argument("-q", "--quiet", action="store_true",
                             help="no progress bars, nothing on stdout (errors and warnings "
                             "still on stderr)")
        return command

    for module_name in COMMAND_MODULES:
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name == module_name:
                continue  # subcommand not built yet
            raise
        module.register(add_command)
    parser.set_defaults(func=lambda args: _usage(parser))
    return parser


def _usage(parser: argparse.ArgumentParser) -> int:
    parser.print_help(sys.stderr)
    return 2


def _one_line_warnings(python_showwarning):
    """A ``warnings.showwarning`` that prints octofactor's own warnings (plug-ins skipped, ...)
    as one clean line on stderr, and others as Python does (a normal run has none)."""

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        from estimation.plugins import PluginWarning

        if issubclass(category, PluginWarning) or category.__module__.split(".")[0] in (
                "estimation", "perception", "mapping", "pipelines"):
            print(f"octofactor: warning: {message}", file=file or sys.stderr)
        else:
            python_showwarning(message, category, filename, lineno, file, line)

    return show


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    return run_command(_call, args)


def entry() -> None:
    """The ``octofactor`` console script (and ``python -m pipelines``): :func:`main`, then exit.

    Everything the command writes is closed by then, so the objects left are frozen
    (``gc.freeze``): the interpreter's last garbage collection skips them and the system
    takes their memory back at exit. atexit handlers and thread joins still run. Measured on
    ``octofactor map`` of the 50 x 100k corridor: 19 -> 8 ms from the end of ``main`` to the
    end of the process. Not done in :func:`main`, which tests and notebooks call in-process.
    """
    import gc

    code = main()
    gc.freeze()
    sys.exit(code)


def _call(args) -> int:
    """Run ``args.func`` with the global switches applied (--deterministic, --quiet)."""
    import os

    tqdm_disable = os.environ.get("TQDM_DISABLE")
    try:
        if getattr(args, "deterministic", False):
            from pipelines.runtime import set_deterministic

            set_deterministic(getattr(args, "seed", None))
        if getattr(args, "quiet", False) and not getattr(args, "dump_config", False):
            import contextlib

            os.environ["TQDM_DISABLE"] = "1"  # every progress bar, in any module
            with open(os.devnull, "w") as devnull, contextlib.redirect_stdout(devnull):
                return int(args.func(args) or 0)
        return int(args.func(args) or 0)
    finally:
        if tqdm_disable is None:
            os.environ.pop("TQDM_DISABLE", None)
        else:
            os.environ["TQDM_DISABLE"] = tqdm_disable


def run_command(func: Callable, args: argparse.Namespace) -> int:
    """Run one command; every error a user can cause becomes one line on stderr and exit 2.

    This is the one place that turns errors into messages: the project's errors
    (OctofactorError), every OSError (missing, unreadable or unwritable files, names over
    255 bytes, a full disk), text files that are not UTF-8, and running out of memory.
    octofactor's own warnings (plug-ins skipped, ...) are one line each as they happen; other
    warnings (NumPy RuntimeWarnings, ...) are held back and printed, one line each, only when
    the command succeeds, so an error line is never preceded by them. SIGTERM and SIGHUP are
    turned into an exception so that temporary files are removed. ``OCTOFACTOR_TRACEBACK=1``
    re-raises instead (for debugging).
    """
    import os
    import re
    import signal
    import warnings

    def on_sigterm(signum, frame):
        raise SystemExit(128 + signum)

    held: list[str] = []
    own = _one_line_warnings(lambda message, *rest: held.append(str(message)))
    with_traceback = os.environ.get("OCTOFACTOR_TRACEBACK") == "1"
    previous = signal.signal(signal.SIGTERM, on_sigterm)
    previous_hup = signal.signal(signal.SIGHUP, on_sigterm)  # a closed terminal
    with warnings.catch_warnings():  # restores the warning display afterwards (tests)
        warnings.showwarning = own
        try:
            status = int(func(args) or 0)
        except KeyboardInterrupt:
            print("octofactor: interrupted", file=sys.stderr)
            return 130
        except BrokenPipeError:  # `octofactor plugins | head`: the reader left, not an error
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            return 0
        except Exception as exc:  # noqa: BLE001 - the one place errors become a line
            if with_traceback:
                raise
            print(f"octofactor: error: {error_line(exc)}", file=sys.stderr)
            return 2
        finally:
            signal.signal(signal.SIGTERM, previous)
            signal.signal(signal.SIGHUP, previous_hup)
    for message in held:
        text = re.sub(r"\x1b\[[0-9;]*m", "", " ".join(message.split()))
        print(f"octofactor: warning: {text}", file=sys.stderr)
    return status


def error_line(exc: BaseException) -> str:
    """The one-line message of an error: file or option first, no traceback."""
    import errno

    from estimation.errors import OctofactorError

    if isinstance(exc, OctofactorError):
        text = str(exc)
    elif isinstance(exc, OSError):
        reason = exc.strerror or str(exc) or type(exc).__name__
        if exc.errno == errno.ENAMETOOLONG:
            reason = "file name too long"
        name = exc.filename if exc.filename is not None else ""
        if exc.filename2 is not None:
            name = f"{name} -> {exc.filename2}"
        text = f"{name}: {reason}" if name else reason
    elif isinstance(exc, UnicodeDecodeError):
        text = (f"a file is not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset "
                f"{exc.start})")
    elif isinstance(exc, MemoryError):
        text = "out of memory (is an input file or option far larger than intended?)"
    else:
        # not an error octofactor raises on purpose: still one line, with its type
        text = f"unexpected {type(exc).__name__}: {exc} (OCTOFACTOR_TRACEBACK=1 shows where)"
    return " ".join(text.split())  # one line


if __name__ == "__main__":
    entry()
