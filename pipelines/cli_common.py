"""Options every ``octofactor`` command shares, so that the commands follow one convention.

* output: always ``-o/--output`` (:func:`add_output`); older spellings (``--out``, a
  positional OUT) still work as hidden, deprecated aliases that print a note.
* ``-q/--quiet`` on every command (added by ``cli.build_parser``): no progress bars and nothing
  on stdout; errors and warnings still go to stderr.
* ``--config FILE`` / ``--dump-config`` on commands with a config dataclass
  (:func:`add_config`, :func:`resolve_config`): the file is the base, flags given on the command
  line override it, and ``--dump-config`` prints the resulting config as TOML and exits, so that
  ``--config <(octofactor CMD ... --dump-config)`` reproduces a run exactly.
* ``--seed N`` and ``--deterministic`` on commands with randomness or threads
  (:func:`add_seed`): see :mod:`pipelines.runtime`.

Nothing heavy is imported here (``octofactor --help`` stays fast).
"""
from __future__ import annotations

import argparse
import sys


class _DeprecatedAlias(argparse.Action):
    """A hidden spelling that still works and says which one to use instead."""

    def __init__(self, option_strings, dest, new: str = "", **kwargs):
        self.new = new
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"octofactor: note: {option_string or self.metavar} is deprecated; use "
              f"{self.new}", file=sys.stderr)
        setattr(namespace, self.dest, values)


def add_output(parser: argparse.ArgumentParser, help: str, required: bool = True,
               metavar: str = "OUTPUT", default: str | None = None,
               old_option: str | None = None, old_positional: bool = False) -> None:
    """``-o/--output`` plus hidden deprecated aliases (``old_option``, a trailing positional).

    With a positional alias, "required" is checked in :func:`output_of` (argparse cannot
    require one of two spellings)."""
    parser.add_argument("-o", "--output", metavar=metavar, help=help, default=default,
                        required=required and not old_positional)
    if old_option:
        parser.add_argument(old_option, dest="output", action=_DeprecatedAlias,
                            new="-o/--output", help=argparse.SUPPRESS, default=argparse.SUPPRESS)
    if old_positional:
        parser.add_argument("_output_positional", nargs="?", metavar="OUTPUT",
                            help=argparse.SUPPRESS, default=None)


def output_of(args) -> str:
    """The output path, from ``-o/--output`` or the deprecated positional."""
    from estimation.errors import OctofactorError

    positional = getattr(args, "_output_positional", None)
    if positional is not None:
        if args.output is not None:
            raise OctofactorError(f"give the output once: -o {args.output} or {positional}")
        print(f"octofactor: note: a positional output ({positional}) is deprecated; use "
              f"-o {positional}", file=sys.stderr)
        return positional
    if args.output is None:
        raise OctofactorError("the output is missing: give -o/--output")
    return args.output


def add_config(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument("--config", metavar="FILE.toml",
                        help=f"read the {what} settings from a TOML file (as written by "
                        "--dump-config); flags given here override it")
    parser.add_argument("--dump-config", action="store_true",
                        help="print the settings as TOML and exit (nothing is run)")


def add_seed(parser: argparse.ArgumentParser, default: int | None, what: str) -> None:
    parser.add_argument("--seed", type=int, default=default,
                        help=f"random seed ({what}; default {default})")
    parser.add_argument("--deterministic", action="store_true",
                        help="bit-identical outputs for the same input and seed: one thread "
                        "for Open3D, OpenCV and numba (slower)")


def base_config(args, cls, default):
    """The config from ``--config FILE`` (a ``cls``), else ``default``."""
    if getattr(args, "config", None):
        from estimation.config import config_from_toml

        return config_from_toml(cls, args.config)
    return default


def dump_config(args, config, command: str) -> bool:
    """Print ``config`` as TOML when ``--dump-config`` was given; True if so."""
    if not getattr(args, "dump_config", False):
        return False
    from estimation.config import config_to_toml

    sys.stdout.write(config_to_toml(config, header=f"octofactor {command} --config FILE "
                                                   f"({type(config).__name__})"))
    return True


def changes(args, mapping: dict[str, str]) -> dict:
    """``{field: value}`` of the flags given on the command line (their default is None)."""
    return {field: getattr(args, dest) for dest, field in mapping.items()
            if getattr(args, dest, None) is not None}
