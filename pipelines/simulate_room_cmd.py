"""`octofactor simulate room OUT_DIR`: the household-room calibration data set (PLY + 4x4 T)."""
from __future__ import annotations


def register(add_command) -> None:
    parser = add_command(
        "room", "simulate a household room: the robot's semantic map and four headset clouds "
                "(PLY) with ground-truth T_map_headset files", group="simulate")
    parser.add_argument("out_dir", metavar="OUT_DIR")
    parser.add_argument("--seed", type=int, default=0, help="random seed (0)")
    parser.add_argument("--label-accuracy", type=float, default=0.9,
                        help="probability that a headset label is right (0.9)")
    parser.add_argument("--robot-label-accuracy", type=float, default=0.95,
                        help="the same for the robot's map (0.95)")
    parser.add_argument("--views", default="tv,desk,shelf,dining",
                        help="comma-separated headset viewpoints (tv,desk,shelf,dining)")
    parser.add_argument("--left-handed", action="store_true",
                        help="write headset clouds in a left-handed frame (z negated)")
    parser.add_argument("--offset-m", type=float, default=1.5,
                        help="size of the ground-truth headset frame offset, m (1.5)")
    parser.add_argument("--offset-deg", type=float, default=60.0,
                        help="its rotation, degrees (up to; 60)")
    parser.add_argument("--image-size", default="320x240", metavar="WxH",
                        help="ray-cast image size of both cameras (320x240)")
    parser.add_argument("--focal", type=float, default=None,
                        help="focal length in pixels (default 0.75 x width)")
    parser.set_defaults(func=run)


def run(args) -> int:
    from estimation.errors import OctofactorError
    from perception.simulation.room import RoomConfig, simulate_room
    from pipelines.validate import room_options

    room_options(args)

    try:
        width, height = (int(v) for v in args.image_size.lower().split("x"))
    except ValueError:
        raise OctofactorError(
            f"--image-size must look like 320x240, got {args.image_size!r}") from None
    from pipelines.validate import image_size

    width, height = image_size("--image-size", width, height)

    config = RoomConfig(seed=args.seed, label_accuracy=args.label_accuracy,
                        robot_label_accuracy=args.robot_label_accuracy,
                        left_handed=args.left_handed, headset_offset_m=args.offset_m,
                        headset_offset_deg=args.offset_deg, image_width=width,
                        image_height=height, focal=args.focal or 0.75 * width)
    views = tuple(v.strip() for v in args.views.split(",") if v.strip())
    written = simulate_room(args.out_dir, config, views)
    for name, path in written.items():
        print(f"{name}: {path}")
    return 0
