"""Checks of command-line options: finite numbers within bounds, named in one-line errors.

Every numeric option a command passes on is checked here (or by the reader it goes to), so
that NaN, inf and absurd sizes fail with ``octofactor: error: --OPTION ...`` and exit 2
instead of crashing a kernel, filling the disk or running for hours. The bounds are generous
limits of what the code is built for, listed in docs/conventions.md.
"""
from __future__ import annotations

import math

from estimation.errors import OctofactorError


class OptionError(OctofactorError):
    """A command-line option is out of range; the message names the option."""


def number(option: str, value, low: float | None = None, high: float | None = None, *,
           low_open: bool = False, allow_none: bool = False) -> float | None:
    """Return ``value`` as a float after checking it is finite and within [low, high].

    ``low_open`` makes the lower bound strict (``value > low``). None passes when
    ``allow_none`` (an option left at its default).
    """
    if value is None and allow_none:
        return None
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise OptionError(f"{option} must be a number, got {value!r}") from None
    if not math.isfinite(x):
        raise OptionError(f"{option} must be a finite number, got {value!r}")
    below = low is not None and (x <= low if low_open else x < low)
    above = high is not None and x > high
    if below or above:
        lo = "" if low is None else (f"> {low:g}" if low_open else f">= {low:g}")
        hi = "" if high is None else f"<= {high:g}"
        raise OptionError(f"{option} must be {' and '.join(p for p in (lo, hi) if p)}, "
                          f"got {value!r}")
    return x


def integer(option: str, value, low: int | None = None, high: int | None = None, *,
            allow_none: bool = False) -> int | None:
    """Return ``value`` as an int after checking it lies within [low, high]."""
    if value is None and allow_none:
        return None
    if isinstance(value, float) and not value.is_integer():
        raise OptionError(f"{option} must be an integer, got {value!r}")
    try:
        n = int(value)
    except (TypeError, ValueError, OverflowError):
        raise OptionError(f"{option} must be an integer, got {value!r}") from None
    if (low is not None and n < low) or (high is not None and n > high):
        bounds = " .. ".join(str(b) for b in (low, high))
        raise OptionError(f"{option} must be an integer in {bounds}, got {value!r}")
    return n


#: seeds accepted by numpy.random.default_rng and stored as uint32 by the simulators
MAX_SEED = 2**32 - 1


def seed(value, option: str = "--seed", allow_none: bool = False) -> int | None:
    return integer(option, value, 0, MAX_SEED, allow_none=allow_none)


# Camera and image limits shared by vp, vpslam and the simulators.
MAX_FOCAL_PX = 1e6
MAX_PRINCIPAL_PX = 1e6
MIN_IMAGE_SIDE = 8
MAX_IMAGE_SIDE = 16384


def intrinsics(option: str, values) -> tuple[float, float, float, float]:
    """Check fx, fy (in (0, 1e6] px) and cx, cy (|.| <= 1e6 px) of an intrinsics option."""
    fx, fy, cx, cy = values
    for name, v in (("fx", fx), ("fy", fy)):
        number(f"{option} {name}", v, 0.0, MAX_FOCAL_PX, low_open=True)
    for name, v in (("cx", cx), ("cy", cy)):
        number(f"{option} {name}", v, -MAX_PRINCIPAL_PX, MAX_PRINCIPAL_PX)
    return float(fx), float(fy), float(cx), float(cy)


def image_size(option: str, width, height) -> tuple[int, int]:
    """Check an image size given as an option (each side MIN_IMAGE_SIDE..MAX_IMAGE_SIDE)."""
    return (integer(f"{option} width", width, MIN_IMAGE_SIDE, MAX_IMAGE_SIDE),
            integer(f"{option} height", height, MIN_IMAGE_SIDE, MAX_IMAGE_SIDE))


def corridor_options(args, config) -> None:
    """Bounds of ``simulate corridor`` on the final CorridorConfig (flags or --config file):
    sizes of a building, a walking pace, at most MAX_CORRIDOR_FRAMES frames."""
    output_folder("-o", output_path(args))
    seed(config.seed)
    length = number("--length", config.length, 0.0, 1000.0, low_open=True)
    number("--width", config.width, 0.5, 100.0)
    number("--height", config.height, 0.5, 100.0)
    speed = number("--speed", config.speed, 0.0, 10.0, low_open=True)
    period = number("--period", config.period, 0.001, 10.0)
    integer("--clutter", config.clutter, 0, 10000)
    frames = length / (speed * period)
    if frames > MAX_CORRIDOR_FRAMES:
        raise OptionError(f"--length / (--speed x --period) gives {frames:.0f} frames, more "
                          f"than {MAX_CORRIDOR_FRAMES}")


MAX_CORRIDOR_FRAMES = 20000


def registration_options(args) -> None:
    """Bounds of ``register`` / ``calibrate``."""
    output_file("-o", output_path(args))
    output_file("--graph", getattr(args, "graph", None))
    registration_numbers(args)


def registration_numbers(args) -> None:
    """The numeric flags of ``register`` / ``calibrate``, before a config is built from them."""
    number("--max-corr", args.max_corr, 0.0, 1e6, low_open=True, allow_none=True)
    number("--initial-corr", args.initial_corr, 0.0, 1e6, low_open=True, allow_none=True)
    number("--alpha", args.alpha, 0.0, 1e6, low_open=True, allow_none=True)
    integer("--max-iterations", args.max_iterations, 1, 100000, allow_none=True)
    systematic_sigma(args.systematic_sigma)
    number("--systematic-rotation-sigma", args.systematic_rotation_sigma, 0.0, math.pi,
           allow_none=True)
    number("--plane-tilt", getattr(args, "plane_tilt", None), 0.0, math.pi, allow_none=True)


def systematic_sigma(text) -> float | tuple[float, float, float] | None:
    """``--systematic-sigma S`` or ``SX,SY,SZ`` (m, each in [0, 1e3]): one number or three."""
    if text is None:
        return None
    parts = str(text).split(",")
    if len(parts) not in (1, 3):
        raise OptionError(f"--systematic-sigma must be one number or three (SX,SY,SZ), "
                          f"got {text!r}")
    values = tuple(number("--systematic-sigma", v, 0.0, 1e3) for v in parts)
    return values[0] if len(values) == 1 else values


def room_options(args) -> None:
    """Bounds of ``simulate room``'s flags (the image size is checked where it is parsed)."""
    output_folder("-o", output_path(args))
    seed(args.seed, allow_none=True)
    number("--label-accuracy", args.label_accuracy, 0.0, 1.0, allow_none=True)
    number("--robot-label-accuracy", args.robot_label_accuracy, 0.0, 1.0, allow_none=True)
    number("--offset-m", args.offset_m, 0.0, 100.0, allow_none=True)
    number("--offset-deg", args.offset_deg, 0.0, 180.0, allow_none=True)
    number("--focal", args.focal, 0.0, MAX_FOCAL_PX, low_open=True, allow_none=True)


def map_options(args) -> None:
    """Bounds of ``map``: a leaf size the octree's float32 keys can hold, a finite range."""
    output_file("-o", output_path(args))
    number("--resolution", args.resolution, 0.0, 1e6, low_open=True)
    if number("--max-range", args.max_range, -1e9, 1e9) == 0.0:
        raise OptionError("--max-range must be positive, or negative for no limit, got 0")


#: the files ``vpslam -o OUT`` writes (pipelines.vpslam.write_outputs)
VPSLAM_OUTPUTS = ("trajectory.txt", "graph.g2o", "graph.g2o.json", "graph.graph", "map.ot",
                  "map.bt", "trajectory.png", "report.json")


def vpslam_options(args) -> None:
    """Bounds of ``vpslam`` (--intrinsics is checked as it is parsed)."""
    import os

    out = output_path(args)
    output_folder("-o", out)
    if out is not None and os.path.isdir(out):  # the files a run writes there, before the run
        for name in VPSLAM_OUTPUTS:
            output_file("-o", os.path.join(out, name))
    number("--depth-scale", args.depth_scale, 0.0, 1e9, low_open=True, allow_none=True)
    number("--vp-distance", args.vp_distance, 0.0, 1e12, low_open=True, allow_none=True)
    number("--gate", args.gate, 0.0, 1e12, low_open=True, allow_none=True)
    number("--resolution", args.resolution, 0.0, 1e6, low_open=True, allow_none=True)
    if number("--max-range", args.max_range, -1e9, 1e9, allow_none=True) == 0.0:
        raise OptionError("--max-range must be positive, or negative for no limit, got 0")
    number("--vo-scale", args.vo_scale, 0.05, 1.0, allow_none=True)
    integer("--max-frames", args.max_frames, 1, 10**9, allow_none=True)


def output_file(option: str, path) -> None:
    """Check an output file before any work: its folder exists and the path is not a link,
    folder or special file (:func:`estimation.fileio.check_output_path`)."""
    import os

    from estimation.fileio import check_output_path

    if path is None:
        return
    check_output_path(path)
    folder = os.path.dirname(os.fspath(path)) or "."
    if not os.path.isdir(folder):
        raise OptionError(f"{option} {path}: folder {folder} does not exist")


def output_folder(option: str, path) -> None:
    """Check an output folder before any work: missing (it is created) or a folder."""
    import os

    if path is not None and os.path.lexists(path) and not os.path.isdir(path):
        raise OptionError(f"{option} {path}: exists and is not a folder")


def output_path(args):
    """The output a command was given (-o/--output or the old positional), None if none
    (``pipelines.cli_common.output_of`` without its note)."""
    positional = getattr(args, "_output_positional", None)
    return positional if positional is not None else getattr(args, "output", None)
