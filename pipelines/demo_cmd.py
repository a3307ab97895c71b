"""`octofactor demo`: the whole mission on built-in synthetic data."""
from __future__ import annotations


def register(add_command) -> None:
    parser = add_command("demo", "run the demo on built-in synthetic data; results in OUT/")
    parser.add_argument("-o", "--out", default="out", help="output folder (default: out)")
    parser.add_argument("--quick", action="store_true", help="smaller data, for tests")
    parser.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from pipelines.demo import run_demo

    run_demo(Path(args.out), quick=args.quick)
    print(f"results in {args.out}/")
    return 0
