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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
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
    import warnings

    parser = build_parser()
    args = parser.parse_args(argv)
    with warnings.catch_warnings():  # restores the warning display afterwards (tests)
        warnings.showwarning = _one_line_warnings(warnings.showwarning)
        return _run(args)


def _run(args) -> int:
    import os

    from estimation.errors import OctofactorError

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
    except OctofactorError as exc:
        print(f"octofactor: error: {exc}", file=sys.stderr)
        return 2
    except (FileNotFoundError, IsADirectoryError, PermissionError, NotADirectoryError) as exc:
        name = exc.filename if exc.filename is not None else ""
        print(f"octofactor: error: {name}: {exc.strerror}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("octofactor: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `octofactor plugins | head`: the reader left, not an error
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    finally:
        if tqdm_disable is None:
            os.environ.pop("TQDM_DISABLE", None)
        else:
            os.environ["TQDM_DISABLE"] = tqdm_disable


if __name__ == "__main__":
    sys.exit(main())
