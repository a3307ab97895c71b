"""`octofactor simulate corridor OUT_DIR`: a monotonous-corridor RGB-D sequence (TUM layout)."""
from __future__ import annotations


def register(add_command) -> None:
    parser = add_command(
        "corridor", "render a monotonous corridor RGB-D sequence (TUM layout) into OUT_DIR",
        group="simulate")
    parser.add_argument("out_dir", metavar="OUT_DIR")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--length", type=float, default=30.0, help="corridor length, m (30)")
    parser.add_argument("--width", type=float, default=2.0, help="corridor width, m (2)")
    parser.add_argument("--height", type=float, default=2.5, help="corridor height, m (2.5)")
    parser.add_argument("--speed", type=float, default=0.8, help="walking speed, m/s (0.8)")
    parser.add_argument("--period", type=float, default=0.3, help="frame period, s (0.3)")
    parser.add_argument("--clutter", type=int, default=0, help="boxes on the floor (0)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)


def run(args) -> int:
    from perception.simulation.corridor import CorridorConfig, simulate_corridor
    from pipelines.validate import corridor_options

    corridor_options(args)

    config = CorridorConfig(seed=args.seed, length=args.length, width=args.width,
                            height=args.height, speed=args.speed, period=args.period,
                            clutter=args.clutter)
    n_frames = simulate_corridor(args.out_dir, config, progress=not args.quiet)
    print(f"{n_frames} frames in {args.out_dir}/")
    return 0
