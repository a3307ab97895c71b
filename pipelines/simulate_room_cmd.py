"""`octofactor simulate room -o OUT_DIR`: the household-room calibration data set (PLY + 4x4 T)."""
from __future__ import annotations

from pipelines.cli_common import add_config, add_output


def register(add_command) -> None:
    parser = add_command(
        "room", "simulate a household room: the robot's semantic map and four headset clouds "
                "(PLY) with ground-truth T_map_headset files", group="simulate")
    add_output(parser, "output folder", metavar="OUT_DIR", old_positional=True)
    parser.add_argument("--seed", type=int, default=None, help="random seed (0)")
    parser.add_argument("--label-accuracy", type=float, default=None,
                        help="probability that a headset label is right (0.9)")
    parser.add_argument("--robot-label-accuracy", type=float, default=None,
                        help="the same for the robot's map (0.95)")
    parser.add_argument("--views", default="tv,desk,shelf,dining",
                        help="comma-separated headset viewpoints (tv,desk,shelf,dining)")
    parser.add_argument("--left-handed", action="store_true", default=None,
                        help="write headset clouds in a left-handed frame (z negated)")
    parser.add_argument("--offset-m", type=float, default=None,
                        help="size of the ground-truth headset frame offset, m (1.5)")
    parser.add_argument("--offset-deg", type=float, default=None,
                        help="its rotation, degrees (up to; 60)")
    parser.add_argument("--image-size", default=None, metavar="WxH",
                        help="ray-cast image size of both cameras (320x240)")
    parser.add_argument("--focal", type=float, default=None,
                        help="focal length in pixels (default 0.75 x width)")
    add_config(parser, "RoomConfig")
    parser.set_defaults(func=run)


def run(args) -> int:
    from dataclasses import replace

    from estimation.errors import OctofactorError
    from perception.simulation.room import RoomConfig, simulate_room
    from pipelines.cli_common import base_config, changes, dump_config, output_of
    from pipelines.validate import room_options

    room_options(args)
    config = base_config(args, RoomConfig, None)
    if config is None:  # the CLI's defaults: 320x240, focal 0.75 x width
        config = RoomConfig(image_width=320, image_height=240, focal=240.0)
    update = changes(args, {"seed": "seed", "label_accuracy": "label_accuracy",
                            "robot_label_accuracy": "robot_label_accuracy",
                            "left_handed": "left_handed", "offset_m": "headset_offset_m",
                            "offset_deg": "headset_offset_deg", "focal": "focal"})
    if args.image_size is not None:
        try:
            width, height = (int(v) for v in args.image_size.lower().split("x"))
        except ValueError:
            raise OctofactorError(
                f"--image-size must look like 320x240, got {args.image_size!r}") from None
        from pipelines.validate import image_size

        width, height = image_size("--image-size", width, height)
        update.update(image_width=width, image_height=height)
        update.setdefault("focal", 0.75 * width)
    config = replace(config, **update)
    if dump_config(args, config, "simulate room"):
        return 0
    views = tuple(v.strip() for v in args.views.split(",") if v.strip())
    written = simulate_room(output_of(args), config, views)
    for name, path in written.items():
        print(f"{name}: {path}")
    return 0
