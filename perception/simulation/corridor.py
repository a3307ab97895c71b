"""A monotonous corridor rendered as an RGB-D sequence (Open3D RaycastingScene, CPU).

World frame: x along the corridor (0 at the back wall, ``length`` at the end wall), y to the
left, z up (floor at z = 0, ceiling at z = ``height``, walls at y = +-width/2). The camera
walks along +x; at zero yaw its optical axis is world +x (camera z -> world +x, camera
x -> world -y, camera y -> world -z), so the forward vanishing point is the image of world +x.

The scene is what the seed paper's robot saw: plain walls, floor and ceiling with slightly
different colours, door frames and panels (edges that the vanishing-point detectors use),
a skirting board, ceiling lamps, faint surface texture (so that photometric odometry has
something) and optional clutter boxes. Depth gets Xtion-like noise: Gaussian with
sigma = ``depth_noise`` * z^2 (Khoshelham & Elberink 2012), optionally a systematic
disparity offset, then the structured-light disparity quantisation (1/8 px, steps of
~z^2 / 315 m), stored with the PNG step 1/depth_scale; nothing nearer than ``min_depth`` or
beyond ``max_depth`` (0.8-3.5 m, the sensor's specified range), nothing at grazing
incidence, and random dropouts.

The colour camera is a consumer one: grey-level noise, lens vignetting (fixed in the image,
so a scene point darkens as it moves outward), a small per-frame auto-exposure change and
motion blur over the shutter time. Together with the short depth range and the faint
texture these are what make frame-to-frame RGB-D odometry drift in such a corridor: on the
default corridor Open3D's hybrid odometry errs by ~2 mrad per frame in pitch, almost
entirely correlated with a vertical translation error (a rotation about the scene ~3 m
ahead), which piles up to metres of height drift over 25 m, as the seed paper reports for
its VO (docs/vp_ekf.md). ``disparity_tilt`` (a depth error linear across the image, as
after a structured-light reference calibrated against a slightly tilted plane) is off by
default.

In memory::

    config = CorridorConfig(seed=3)
    scene = build_corridor_scene(config)
    stamps, poses = corridor_trajectory(config)          # poses: T_world_camera
    rng = np.random.default_rng(0)                       # None: noise-free images
    rgb, depth_m = render_frame(scene, poses[0], config.intrinsics, rng)

On disk: :func:`simulate_corridor` writes the TUM layout that
:class:`perception.rgbd.TumRgbdSequence` reads, plus ``vps.txt`` (ground-truth forward VP).
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import gtsam
import numpy as np

from estimation.fileio import atomic_write
from perception.errors import PerceptionError
from perception.rgbd import (
    CAMERA_FILE_NAME,
    CameraIntrinsics,
    encode_depth_png,
    encode_rgb_png,
    write_camera_file,
)

XTION_640 = CameraIntrinsics(525.0, 525.0, 319.5, 239.5, 640, 480, 5000.0)

# camera axes in the world at zero yaw: columns are camera x, y, z
R_WORLD_CAMERA_FORWARD = np.array([[0.0, 0.0, 1.0],
                                   [-1.0, 0.0, 0.0],
                                   [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class CorridorConfig:
    """Everything that defines a simulated corridor sequence (deterministic for ``seed``).

    Attributes
    ----------
    seed : int
        Seeds door placement, texture, clutter, image and depth noise.
    length, width, height : float
        Corridor size in metres (world x, y, z).
    speed : float
        Walking speed along +x (m/s).
    period : float
        Frame period (s); the Xtion sequence of the paper was logged at ~300 ms.
    clutter : int
        Number of boxes standing on the floor along the walls.
    camera_height : float
        Camera centre above the floor (m).
    start_x, end_margin : float
        The walk starts at x = start_x and stops ``end_margin`` before the end wall.
    zigzag_amplitude, zigzag_wavelength : float
        Lateral sway y = A sin(2 pi x / wavelength) (m) of the walking path.
    yaw_amplitude_deg, pitch_amplitude_deg, roll_amplitude_deg : float
        Small head motions (degrees); yaw follows the zigzag, pitch/roll bob at other rates.
    mount_pitch_deg : float
        A constant pitch of the camera (degrees, nose down for positive): a sensor mounted
        slightly tilted, as on a real robot or helmet.
    depth_noise : float
        Axial depth noise coefficient: sigma = depth_noise * z^2 (m); 0 disables noise.
        Default 1.425e-3 (Kinect, Khoshelham & Elberink 2012).
    min_depth, max_depth : float
        Depth measured only in [min_depth, max_depth] (m). Default 0.8-3.5 m: the Xtion
        Pro Live's specified range (the seed paper's Table 1).
    dropout : float
        Probability that a depth pixel is missing at random.
    disparity_step : float
        Structured-light quantisation: disparity (pixels, f * baseline / z) is rounded to
        this step (Kinect/Xtion: 1/8 px), giving depth steps of z^2 step / (f baseline);
        0 disables it.
    baseline : float
        Projector-camera baseline (m) for the disparity quantisation (Xtion: 0.075).
    grazing_cos : float
        Depth is missing where |cos(incidence)| < grazing_cos.
    disparity_tilt : tuple of float
        Systematic disparity offset (pixels) at the right and at the bottom image edge,
        linear across the image (a reference pattern calibrated against a slightly tilted
        plane; see the module notes); 0 disables it.
    rgb_noise : float
        Standard deviation of the colour noise (grey levels; default 2, a consumer
        sensor's luminance noise indoors).
    vignetting : float
        Relative brightness loss at the image corners, falling off with the squared
        distance from the principal point (default 0.1; 0: none). Moving scene points
        change brightness across the image, against photometric odometry's assumption.
    exposure_jitter : float
        Standard deviation of the per-frame log exposure gain (auto-exposure; default
        0.005, i.e. ~1 grey level; 0: none).
    exposure_time : float
        Shutter time (s): the colour image integrates the motion over
        [t - exposure_time, t] (motion blur; default 10 ms; 0: none); depth and ground
        truth are at t.
    blur_samples : int
        Sub-images averaged for the motion blur.
    texture : float
        Relative amplitude of the faint surface texture (0 = flat colours; default 0.03:
        painted walls, a feature-poor corridor).
    door_spacing : float
        Mean distance between doors along the corridor (alternating sides).
    intrinsics : CameraIntrinsics
        640x480, fx = fy = 525, (cx, cy) = (319.5, 239.5), depth scale 5000.
    """

    seed: int = 0
    length: float = 30.0
    width: float = 2.0
    height: float = 2.5
    speed: float = 0.8
    period: float = 0.3
    clutter: int = 0
    camera_height: float = 1.2
    start_x: float = 0.5
    end_margin: float = 2.0
    zigzag_amplitude: float = 0.12
    zigzag_wavelength: float = 4.8
    yaw_amplitude_deg: float = 3.0
    pitch_amplitude_deg: float = 1.0
    roll_amplitude_deg: float = 0.5
    mount_pitch_deg: float = 0.0
    depth_noise: float = 1.425e-3
    min_depth: float = 0.8
    max_depth: float = 3.5
    dropout: float = 0.01
    disparity_step: float = 0.125
    baseline: float = 0.075
    grazing_cos: float = 0.08
    disparity_tilt: tuple[float, float] = (0.0, 0.0)
    rgb_noise: float = 2.0
    vignetting: float = 0.1
    exposure_jitter: float = 0.005
    exposure_time: float = 0.01
    blur_samples: int = 3
    texture: float = 0.03
    door_spacing: float = 4.0
    intrinsics: CameraIntrinsics = field(default=XTION_640)

    def validate(self) -> None:
        """Raise PerceptionError when the corridor or the walk cannot be built."""
        numbers = [v for v in vars(self).values() if isinstance(v, (int, float))]
        if not all(np.isfinite(numbers)) or not np.all(np.isfinite(self.disparity_tilt)):
            raise PerceptionError("corridor parameters must be finite numbers (no NaN or inf)")
        if min(self.length, self.width, self.height, self.speed, self.period) <= 0:
            raise PerceptionError("length, width, height, speed and period must be positive")
        if not 0 < self.camera_height < self.height:
            raise PerceptionError("camera_height must lie between the floor and the ceiling")
        if self.length - self.end_margin - self.start_x < self.speed * self.period:
            raise PerceptionError(f"corridor of length {self.length} m is too short for one "
                                  f"step of {self.speed * self.period:.3f} m")
        if abs(self.zigzag_amplitude) >= self.width / 2:
            raise PerceptionError("zigzag_amplitude must be less than half the width")
        if self.clutter < 0 or not 0 <= self.dropout < 1:
            raise PerceptionError("clutter must be >= 0 and dropout in [0, 1)")
        if not 0 <= self.vignetting < 1 or self.exposure_jitter < 0 or self.exposure_time < 0:
            raise PerceptionError("vignetting must be in [0, 1), exposure_jitter and "
                                  "exposure_time >= 0")
        if not abs(self.mount_pitch_deg) <= 45.0:  # also refuses NaN
            raise PerceptionError("mount_pitch_deg must be within +-45 degrees")
        if self.blur_samples < 1 or len(self.disparity_tilt) != 2:
            raise PerceptionError("blur_samples must be >= 1 and disparity_tilt two numbers")


@dataclass(frozen=True)
class CorridorScene:
    """A built corridor: the ray-casting scene and what shading needs per triangle.

    Attributes
    ----------
    raycasting : open3d.t.geometry.RaycastingScene
    triangle_albedo : np.ndarray
        (T, 3) float32 RGB albedo in [0, 1] of every triangle of every geometry.
    geometry_offset : np.ndarray
        (G,) int64: the first row of ``triangle_albedo`` of each geometry id.
    lamps : np.ndarray
        (L, 3) world positions of the ceiling lamps (point lights).
    texture : np.ndarray
        (N, N) float32 zero-mean smooth random field, 2 cm texels.
    config : CorridorConfig
    """

    raycasting: object
    triangle_albedo: np.ndarray
    geometry_offset: np.ndarray
    lamps: np.ndarray
    texture: np.ndarray
    config: CorridorConfig


_TEXEL = 0.02       # texture cell (m): a few pixels at corridor distances
_TEXTURE_SIZE = 256

_WALL = (0.80, 0.78, 0.72)
_FLOOR = (0.55, 0.52, 0.48)
_CEILING = (0.92, 0.92, 0.90)
_END_WALL = (0.74, 0.76, 0.78)
_DOOR = (0.50, 0.40, 0.30)
_FRAME = (0.45, 0.45, 0.47)
_SKIRTING = (0.35, 0.33, 0.30)
_LAMP = (1.00, 1.00, 0.97)


def _box(lo, hi):
    """An axis-aligned box mesh (Open3D tensor mesh) from corner ``lo`` to ``hi``."""
    import open3d as o3d

    lo = np.asarray(lo, dtype=float)
    size = np.asarray(hi, dtype=float) - lo
    mesh = o3d.t.geometry.TriangleMesh.create_box(float(size[0]), float(size[1]), float(size[2]))
    return mesh.translate(lo)


def build_corridor_scene(config: CorridorConfig = CorridorConfig()) -> CorridorScene:
    """Return the ray-casting scene of the corridor described by ``config``."""
    import open3d as o3d

    config.validate()
    rng = np.random.default_rng([config.seed, 1])
    L, W, H = config.length, config.width, config.height
    half = W / 2
    parts: list[tuple[object, np.ndarray]] = []

    def add(lo, hi, albedo, face_albedo=None):
        mesh = _box(lo, hi)
        normals = _triangle_normals(mesh)
        colours = np.tile(np.asarray(albedo, dtype=np.float32), (normals.shape[0], 1))
        if face_albedo is not None:
            colours = face_albedo(normals).astype(np.float32)
        parts.append((mesh, colours))

    def shell_colours(normals):
        # the shell is seen from inside: its triangle normals point outward
        colours = np.empty((normals.shape[0], 3), dtype=np.float32)
        axis = np.argmax(np.abs(normals), axis=1)
        colours[:] = _WALL
        colours[(axis == 2) & (normals[:, 2] < 0)] = _FLOOR
        colours[(axis == 2) & (normals[:, 2] > 0)] = _CEILING
        colours[axis == 0] = _END_WALL
        return colours

    add((0.0, -half, 0.0), (L, half, H), None, shell_colours)
    # skirting boards: a 1 cm step along both walls gives the floor/wall edge some depth
    add((0.0, -half, 0.0), (L, -half + 0.012, 0.08), _SKIRTING)
    add((0.0, half - 0.012, 0.0), (L, half, 0.08), _SKIRTING)

    door_width, door_height, jamb, protrusion = 0.9, 2.05, 0.06, 0.04
    x = config.start_x + 1.5 + rng.uniform(0, config.door_spacing / 2)
    side = 1.0 if rng.uniform() < 0.5 else -1.0
    while x + door_width + 2 * jamb < L - 0.3:
        wall = side * half
        inward = -side  # +y for the right wall (y = -half), -y for the left one
        def yspan(depth, wall=wall, inward=inward):
            a, b = wall, wall + inward * depth
            return min(a, b), max(a, b)
        y0, y1 = yspan(0.015)
        add((x + jamb, y0, 0.0), (x + jamb + door_width, y1, door_height), _DOOR)
        y0, y1 = yspan(protrusion)
        add((x, y0, 0.0), (x + jamb, y1, door_height + jamb), _FRAME)
        add((x + jamb + door_width, y0, 0.0), (x + 2 * jamb + door_width, y1,
                                                door_height + jamb), _FRAME)
        add((x + jamb, y0, door_height), (x + jamb + door_width, y1, door_height + jamb), _FRAME)
        x += config.door_spacing * rng.uniform(0.7, 1.3)
        side = -side

    lamps = []
    for lamp_x in np.arange(2.0, L - 0.5, 3.0):
        add((lamp_x - 0.3, -0.15, H - 0.02), (lamp_x + 0.3, 0.15, H), _LAMP)
        lamps.append((lamp_x, 0.0, H - 0.05))

    for _ in range(config.clutter):
        size = rng.uniform([0.3, 0.3, 0.3], [0.7, 0.6, 0.9])
        bx = rng.uniform(config.start_x + 1.0, L - size[0])
        by = half - size[1] - 0.02 if rng.uniform() < 0.5 else -half + 0.02
        albedo = rng.uniform(0.3, 0.8, size=3)
        add((bx, by, 0.0), (bx + size[0], by + size[1], size[2]), albedo)

    scene = o3d.t.geometry.RaycastingScene()
    offsets = []
    albedo_rows = []
    total = 0
    for mesh, colours in parts:
        geometry_id = scene.add_triangles(mesh)
        if geometry_id != len(offsets):
            raise PerceptionError("Open3D returned unexpected geometry ids")
        offsets.append(total)
        albedo_rows.append(colours)
        total += colours.shape[0]

    noise = rng.standard_normal((_TEXTURE_SIZE, _TEXTURE_SIZE)).astype(np.float32)
    texture = _smooth_periodic(noise, sigma_texels=1.2)
    texture /= max(float(np.std(texture)), 1e-6)
    return CorridorScene(scene, np.concatenate(albedo_rows), np.asarray(offsets, np.int64),
                         np.asarray(lamps, dtype=np.float32).reshape(-1, 3), texture, config)


def _triangle_normals(mesh) -> np.ndarray:
    vertices = mesh.vertex.positions.numpy().astype(np.float64)
    triangles = mesh.triangle.indices.numpy()
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    normals = np.cross(b - a, c - a)
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def _smooth_periodic(field_: np.ndarray, sigma_texels: float) -> np.ndarray:
    """Gaussian-blur a periodic field in the Fourier domain (the texture tiles seamlessly)."""
    freq = np.fft.fftfreq(field_.shape[0])
    gain = np.exp(-2 * (np.pi * sigma_texels) ** 2 * (freq[:, None] ** 2 + freq[None, :] ** 2))
    return np.real(np.fft.ifft2(np.fft.fft2(field_) * gain)).astype(np.float32)


def corridor_trajectory(config: CorridorConfig = CorridorConfig(), time_offset: float = 0.0
                        ) -> tuple[np.ndarray, list[gtsam.Pose3]]:
    """Return (timestamps (N,) s, poses T_world_camera) of the walk along the corridor.

    x = start_x + speed t, y = A sin(2 pi x / wavelength), z = camera_height; yaw follows the
    sway (peak ``yaw_amplitude_deg`` where the path crosses the centre line), pitch and roll
    bob slowly. Timestamps are k * period; the poses are taken at the timestamps plus
    ``time_offset`` (``-config.exposure_time``: where each exposure starts).
    """
    config.validate()
    travel = config.length - config.end_margin - config.start_x
    n_frames = int(np.floor(travel / (config.speed * config.period) + 1e-9)) + 1
    stamps = np.arange(n_frames) * config.period
    x = config.start_x + config.speed * (stamps + time_offset)
    phase = 2 * np.pi * (x - config.start_x) / config.zigzag_wavelength
    y = config.zigzag_amplitude * np.sin(phase)
    yaw = np.deg2rad(config.yaw_amplitude_deg) * np.cos(phase)
    pitch = (np.deg2rad(config.pitch_amplitude_deg) * np.sin(0.37 * phase + 0.5)
             + np.deg2rad(config.mount_pitch_deg))
    roll = np.deg2rad(config.roll_amplitude_deg) * np.sin(0.61 * phase + 1.3)
    poses = []
    base = gtsam.Rot3(R_WORLD_CAMERA_FORWARD)
    for k in range(n_frames):
        # yaw about world z, pitch about world y (nose down for positive), roll about world x
        head = gtsam.Rot3.Ypr(yaw[k], pitch[k], roll[k])
        poses.append(gtsam.Pose3(head.compose(base),
                                 np.array([x[k], y[k], config.camera_height])))
    return stamps, poses


def forward_vanishing_point(T_world_camera: gtsam.Pose3, intr: CameraIntrinsics
                            ) -> tuple[np.ndarray, np.ndarray | None]:
    """Return (direction (3,) unit in the camera frame, pixel (2,) or None) of world +x."""
    direction = T_world_camera.rotation().unrotate(np.array([1.0, 0.0, 0.0]))
    direction = np.asarray(direction, dtype=float)
    if direction[2] < 0:
        direction = -direction
    if direction[2] < 1e-9:
        return direction, None
    uv = intr.K @ (direction / direction[2])
    return direction, uv[:2]


def _pixel_directions(intr: CameraIntrinsics) -> np.ndarray:
    """(H*W, 3) camera-frame ray directions with unit z, so that t_hit is the z-depth."""
    u, v = np.meshgrid(np.arange(intr.width, dtype=np.float64),
                       np.arange(intr.height, dtype=np.float64))
    return np.stack([(u.ravel() - intr.cx) / intr.fx, (v.ravel() - intr.cy) / intr.fy,
                     np.ones(u.size)], axis=1).astype(np.float32)


def render_frame(scene: CorridorScene, T_world_camera: gtsam.Pose3, intr: CameraIntrinsics,
                 rng: np.random.Generator | None = None,
                 T_world_camera_open: gtsam.Pose3 | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Return (rgb (H,W,3) uint8, depth_m (H,W) float32) seen from ``T_world_camera``.

    With ``rng`` None the images are noise-free (exact z-depth, no dropouts, no quantisation,
    no exposure change, only the min/max depth limits and the lens vignetting); with an
    ``rng`` the depth gets the Xtion-like noise and systematic disparity offset of
    ``scene.config`` and is quantised to 1/depth_scale, and the colour gets the exposure
    change and pixel noise. ``T_world_camera_open`` (the pose when the shutter opened, e.g.
    from ``corridor_trajectory(config, -config.exposure_time)``) adds the motion blur of
    the path from there to ``T_world_camera``. Depth 0 means no measurement.
    """
    import open3d as o3d

    config = scene.config
    key = (intr, config.vignetting, tuple(config.disparity_tilt))
    if key not in _PIXEL_CACHE:
        _PIXEL_CACHE[key] = _pixel_maps(intr, config)
    directions_camera, vignette, disparity_offset = _PIXEL_CACHE[key]
    make_rays, shade, _ = _kernels()
    rays = make_rays(directions_camera, T_world_camera.rotation().matrix().astype(np.float32),
                     np.asarray(T_world_camera.translation(), dtype=np.float32))
    hits = scene.raycasting.cast_rays(o3d.core.Tensor.from_numpy(rays))
    noisy = rng is not None
    # one seed per frame drawn from the caller's generator: a seed gives identical frames
    frame_seed = int(rng.integers(0, 2 ** 31 - 1)) if noisy else 0
    t_hit = hits["t_hit"].numpy()
    radiance, depth = shade(
        rays, t_hit, hits["geometry_ids"].numpy(),
        hits["primitive_ids"].numpy(), hits["primitive_normals"].numpy(),
        scene.geometry_offset, scene.triangle_albedo, scene.lamps, scene.texture,
        np.float32(config.texture), np.float32(_TEXEL), noisy, frame_seed,
        np.float32(config.depth_noise), np.float32(config.dropout),
        np.float32(config.grazing_cos), np.float32(config.min_depth),
        np.float32(config.max_depth), np.float32(intr.depth_scale),
        np.float64(intr.fx * config.baseline), np.float64(config.disparity_step),
        disparity_offset)
    radiance = radiance.reshape(intr.height, intr.width, 3)
    if (T_world_camera_open is not None and config.exposure_time > 0
            and config.blur_samples > 1):
        radiance = _motion_blur(radiance, t_hit, directions_camera,
                                T_world_camera_open.between(T_world_camera), intr,
                                config.blur_samples)
    gain = vignette
    if noisy:
        frame_rng = np.random.default_rng(frame_seed)
        if config.exposure_jitter > 0:
            gain = gain * np.float32(np.exp(config.exposure_jitter
                                            * frame_rng.standard_normal()))
        # one grey-level noise value per pixel (the sensor's luminance noise)
        grey = frame_rng.standard_normal((intr.height, intr.width), dtype=np.float32)
        value = radiance * gain[..., None] + (np.float32(config.rgb_noise) * grey)[..., None]
    else:
        value = radiance * gain[..., None]
    rgb = np.clip(np.rint(value), 0, 255).astype(np.uint8)
    if noisy:
        # the same float32 division as perception.rgbd.read_depth: files and memory agree
        depth = np.minimum(depth, np.float32(np.iinfo(np.uint16).max)) / np.float32(
            intr.depth_scale)
    return rgb, depth.reshape(intr.height, intr.width)


def _pixel_maps(intr: CameraIntrinsics, config: CorridorConfig
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ray directions (H*W, 3), vignetting gain (H, W), disparity offset (H*W,)) per pixel."""
    directions = _pixel_directions(intr)
    u, v = np.meshgrid(np.arange(intr.width, dtype=np.float64),
                       np.arange(intr.height, dtype=np.float64))
    du, dv = u - intr.cx, v - intr.cy
    corner2 = max(intr.cx, intr.width - 1 - intr.cx) ** 2 + max(
        intr.cy, intr.height - 1 - intr.cy) ** 2
    vignette = (1.0 - config.vignetting * (du ** 2 + dv ** 2) / corner2).astype(np.float32)
    tilt_u, tilt_v = config.disparity_tilt
    offset = (tilt_u * du / max(intr.width - 1 - intr.cx, 1.0)
              + tilt_v * dv / max(intr.height - 1 - intr.cy, 1.0))
    return directions, vignette, offset.ravel().astype(np.float64)


def _motion_blur(radiance: np.ndarray, t_hit: np.ndarray, directions: np.ndarray,
                 T_open_close: gtsam.Pose3, intr: CameraIntrinsics, samples: int) -> np.ndarray:
    """The image averaged over the exposure: each pixel sampled along its own image motion.

    The flow of every pixel from the shutter-open camera to the final one follows from its
    noise-free depth (linear in time; occlusions during the exposure are ignored, they are
    sub-pixel here). ``cv2.remap`` samples the final image along that path.
    """
    import cv2

    flow = _kernels()[2]
    # where a pixel's scene point sits in the final image earlier in the exposure
    flow_u, flow_v = flow(directions, t_hit, T_open_close.rotation().matrix(),
                          np.asarray(T_open_close.translation(), dtype=np.float64),
                          intr.fx, intr.fy, intr.cx, intr.cy, intr.width)
    shape = (intr.height, intr.width)
    flow_u, flow_v = flow_u.reshape(shape), flow_v.reshape(shape)
    u, v = np.meshgrid(np.arange(intr.width, dtype=np.float32),
                       np.arange(intr.height, dtype=np.float32))
    total = np.zeros_like(radiance)
    for s in np.linspace(0.0, 1.0, samples, dtype=np.float32):
        total += cv2.remap(radiance, u + s * flow_u, v + s * flow_v, cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_REPLICATE)
    return total / np.float32(samples)


_PIXEL_CACHE: dict = {}
_KERNELS = None


def _kernels():
    """The compiled ray and per-pixel shading kernels (numba, compiled on first use, cached).

    Per pixel: albedo of the hit triangle x (ambient + diffuse light of the ceiling lamps,
    which are fixed in the world) x (1 + faint texture), in grey levels before the camera's
    vignetting, exposure gain and noise (applied by :func:`render_frame`). The texture is a
    bilinear lookup of a periodic random field in each plane's own two coordinates. Depth:
    Xtion-like noise on the z-depth, the systematic disparity offset, then the disparity
    quantisation.
    """
    global _KERNELS
    if _KERNELS is not None:
        return _KERNELS
    import numba

    texture_size = _TEXTURE_SIZE

    @numba.njit(cache=True, nogil=True)
    def make_rays(directions, R, origin):
        n = directions.shape[0]
        rays = np.empty((n, 6), dtype=np.float32)
        for i in range(n):
            dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
            for r in range(3):
                rays[i, r] = origin[r]
                rays[i, 3 + r] = R[r, 0] * dx + R[r, 1] * dy + R[r, 2] * dz
        return rays

    @numba.njit(cache=True, fastmath=True, nogil=True)
    def kernel(rays, t_hit, geometry, primitive, normals, offsets, albedo, lamps, texture,
               amplitude, texel, noisy, seed, depth_coefficient, dropout,
               grazing_cos, min_depth, max_depth, depth_scale, focal_baseline,
               disparity_step, disparity_offset):
        if noisy:
            np.random.seed(seed)  # numba's own generator state, not NumPy's
        n = t_hit.shape[0]
        out = np.zeros((n, 3), dtype=np.float32)
        depth = np.zeros(n, dtype=np.float32)
        for i in range(n):
            t = t_hit[i]
            if not np.isfinite(t):
                continue
            dx0, dy0, dz0 = rays[i, 3], rays[i, 4], rays[i, 5]
            px = rays[i, 0] + dx0 * t
            py = rays[i, 1] + dy0 * t
            pz = rays[i, 2] + dz0 * t
            nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
            shade = np.float32(0.45)
            for k in range(lamps.shape[0]):
                dx = lamps[k, 0] - px
                # a smooth 6 m window (fixed in the world) skips the far lamps cheaply
                if abs(dx) > 6.0:
                    continue
                window = 1.0 - (dx / 6.0) ** 2
                dy = lamps[k, 1] - py
                dz = lamps[k, 2] - pz
                dist2 = dx * dx + dy * dy + dz * dz + np.float32(0.25)
                cos = abs(dx * nx + dy * ny + dz * nz) / np.sqrt(dist2)
                shade += np.float32(0.9) * window * window * cos / dist2
            shade = min(shade, np.float32(1.2))
            ax, ay, az = abs(nx), abs(ny), abs(nz)
            # plane coordinates: x-facing -> (y, z), y-facing -> (x, z), z-facing -> (x, y);
            # a per-orientation offset so walls and floor do not show the same pattern
            if ax >= ay and ax >= az:
                s, r, offset = py, pz, 0.0
            elif ay >= az:
                s, r, offset = px, pz, 1.0
            else:
                s, r, offset = px, py, 2.0
            s = s / texel + offset * 71.0
            r = r / texel + offset * 37.0
            s0 = np.floor(s)
            r0 = np.floor(r)
            fs = s - s0
            fr = r - r0
            i0 = int(s0) % texture_size
            j0 = int(r0) % texture_size
            i1 = (i0 + 1) % texture_size
            j1 = (j0 + 1) % texture_size
            tex = ((texture[j0, i0] * (1 - fs) + texture[j0, i1] * fs) * (1 - fr)
                   + (texture[j1, i0] * (1 - fs) + texture[j1, i1] * fs) * fr)
            gain = shade * (1.0 + amplitude * tex) * 255.0
            row = offsets[geometry[i]] + primitive[i]
            for c in range(3):
                out[i, c] = albedo[row, c] * gain
            # depth: t is the z-depth because the camera-frame ray has unit z
            if t < min_depth or t > max_depth:
                continue
            if noisy:
                ray_norm = np.sqrt(dx0 * dx0 + dy0 * dy0 + dz0 * dz0)
                cos_incidence = abs(dx0 * nx + dy0 * ny + dz0 * nz) / ray_norm
                if np.random.random() < dropout or cos_incidence < grazing_cos:
                    continue
                # Xtion-like: sigma grows with z^2; stored with the PNG's step 1/depth_scale
                # (stored as PNG counts here; divided outside exactly as the reader does)
                z = t + depth_coefficient * np.random.standard_normal() * t * t
                disparity = focal_baseline / z + disparity_offset[i]
                if disparity_step > 0.0:
                    disparity = np.rint(disparity / disparity_step) * disparity_step
                if disparity <= 0.0:
                    continue
                z = focal_baseline / disparity
                if z < min_depth or z > max_depth:
                    continue
                depth[i] = np.rint(z * depth_scale)
            else:
                depth[i] = t
        return out, depth

    @numba.njit(cache=True, nogil=True)
    def flow(directions, t_hit, R, t, fx, fy, cx, cy, width):
        # the final camera's point of each pixel seen from the shutter-open camera
        n = t_hit.shape[0]
        flow_u = np.zeros(n, dtype=np.float32)
        flow_v = np.zeros(n, dtype=np.float32)
        for i in range(n):
            depth = t_hit[i]
            if not np.isfinite(depth):
                continue
            px, py, pz = directions[i, 0] * depth, directions[i, 1] * depth, depth
            x = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
            y = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
            z = max(R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2], 1e-3)
            flow_u[i] = (i % width) - (fx * x / z + cx)
            flow_v[i] = (i // width) - (fy * y / z + cy)
        return flow_u, flow_v

    _KERNELS = (make_rays, kernel, flow)
    return _KERNELS


def simulate_corridor(out_dir: str | os.PathLike, config: CorridorConfig = CorridorConfig(),
                      progress: bool = False) -> int:
    """Write the corridor sequence to ``out_dir`` in the TUM layout; return the frame count.

    Files: ``rgb/<t>.png``, ``depth/<t>.png`` (uint16, metres x depth_scale), ``rgb.txt``,
    ``depth.txt``, ``groundtruth.txt`` (t tx ty tz qx qy qz qw, T_world_camera),
    ``camera.txt`` (docs/camera_file.md) and ``vps.txt`` (t u v dx dy dz: the forward
    vanishing point, pixel and camera-frame unit direction; u v are ``nan`` at infinity).
    Identical for identical ``config`` (all randomness comes from ``config.seed``).
    """
    out = Path(out_dir)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    intr = config.intrinsics
    scene = build_corridor_scene(config)
    stamps, poses = corridor_trajectory(config)
    open_poses = (corridor_trajectory(config, -config.exposure_time)[1]
                  if config.exposure_time > 0 else [None] * len(poses))
    rng = np.random.default_rng([config.seed, 2])
    names = [f"{stamp:.6f}.png" for stamp in stamps]
    frames = range(len(stamps))
    if progress:
        from tqdm import tqdm

        frames = tqdm(frames, desc="corridor", unit="frame")
    for k in frames:
        rgb, depth = render_frame(scene, poses[k], intr, rng, open_poses[k])
        with atomic_write(out / "rgb" / names[k], "wb") as handle:
            handle.write(encode_rgb_png(rgb))
        with atomic_write(out / "depth" / names[k], "wb") as handle:
            handle.write(encode_depth_png(depth, intr.depth_scale))
    header = f"# octofactor simulated corridor, seed {config.seed}\n"
    for kind in ("rgb", "depth"):
        with atomic_write(out / f"{kind}.txt", "w") as handle:
            handle.write(header + "# timestamp filename\n")
            for stamp, name in zip(stamps, names):
                handle.write(f"{stamp:.6f} {kind}/{name}\n")
    with atomic_write(out / "groundtruth.txt", "w") as handle:
        handle.write(header + "# timestamp tx ty tz qx qy qz qw (T_world_camera)\n")
        for stamp, pose in zip(stamps, poses):
            q = pose.rotation().toQuaternion()
            tx, ty, tz = np.asarray(pose.translation())
            handle.write(f"{stamp:.6f} {tx:.9f} {ty:.9f} {tz:.9f} "
                         f"{q.x():.12f} {q.y():.12f} {q.z():.12f} {q.w():.12f}\n")
    with atomic_write(out / "vps.txt", "w") as handle:
        handle.write(header + "# timestamp u v dx dy dz: forward vanishing point (world +x); "
                              "direction in the camera frame (x right, y down, z forward)\n")
        for stamp, pose in zip(stamps, poses):
            direction, uv = forward_vanishing_point(pose, intr)
            u, v = (np.nan, np.nan) if uv is None else uv
            handle.write(f"{stamp:.6f} {u:.6f} {v:.6f} {direction[0]:.12f} "
                         f"{direction[1]:.12f} {direction[2]:.12f}\n")
    write_camera_file(out / CAMERA_FILE_NAME, intr)
    return len(stamps)


def read_vps_file(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (timestamps (N,), uv (N,2) with nan at infinity, directions (N,3)) of vps.txt."""
    from estimation.errors import FormatError

    path = Path(path)
    if not path.is_file():
        raise FormatError(path, "vanishing-point file not found")
    try:
        data = np.loadtxt(path, comments="#", ndmin=2)
    except ValueError as exc:
        raise FormatError(path, f"expected rows 't u v dx dy dz': {exc}") from None
    if data.shape[1] != 6:
        raise FormatError(path, f"expected 6 columns 't u v dx dy dz', found {data.shape[1]}")
    return data[:, 0], data[:, 1:3], data[:, 3:6]
