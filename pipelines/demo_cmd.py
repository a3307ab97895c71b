"""`octofactor demo`: the whole mission on built-in synthetic data."""
from __future__ import annotations

from pipelines.cli_common import add_output


def register(add_command) -> None:
    parser = add_command("demo", "run the demo on built-in synthetic data; results in OUT/")
    add_output(parser, "output folder (default: out)", required=False, default="out",
               metavar="OUT_DIR", old_option="--out")
    parser.add_argument("--quick", action="store_true", help="smaller data, for tests")
    parser.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from pipelines.demo import run_demo

    run_demo(Path(args.output), quick=args.quick)
    print(f"results in {args.output}/")
    return 0
