"""`octofactor simulate corridor -o OUT_DIR`: a monotonous-corridor RGB-D sequence (TUM layout)."""
from __future__ import annotations

from pipelines.cli_common import add_config, add_output


def register(add_command) -> None:
    parser = add_command(
        "corridor", "render a monotonous corridor RGB-D sequence (TUM layout) into OUT_DIR",
        group="simulate")
    add_output(parser, "output folder (TUM layout)", metavar="OUT_DIR", old_positional=True)
    parser.add_argument("--seed", type=int, default=None, help="random seed (default 0)")
    parser.add_argument("--length", type=float, default=None, help="corridor length, m (30)")
    parser.add_argument("--width", type=float, default=None, help="corridor width, m (2)")
    parser.add_argument("--height", type=float, default=None, help="corridor height, m (2.5)")
    parser.add_argument("--speed", type=float, default=None, help="walking speed, m/s (0.8)")
    parser.add_argument("--period", type=float, default=None, help="frame period, s (0.3)")
    parser.add_argument("--clutter", type=int, default=None, help="boxes on the floor (0)")
    add_config(parser, "CorridorConfig")
    parser.set_defaults(func=run)


def run(args) -> int:
    from dataclasses import replace

    from perception.simulation.corridor import CorridorConfig, simulate_corridor
    from pipelines.cli_common import base_config, changes, dump_config, output_of

    config = replace(base_config(args, CorridorConfig, CorridorConfig()), **changes(args, {
        name: name for name in ("seed", "length", "width", "height", "speed", "period",
                                "clutter")}))
    if dump_config(args, config, "simulate corridor"):
        return 0
    from pipelines.validate import corridor_options

    corridor_options(args, config)
    out_dir = output_of(args)
    n_frames = simulate_corridor(out_dir, config, progress=not args.quiet)
    print(f"{n_frames} frames in {out_dir}/")
    return 0
