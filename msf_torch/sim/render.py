"""Rendered stereo image sequences along simulated runs (OpenCV and numpy).

The scene is world-fixed, so a trajectory that comes back to a place sees it again (loop
sequences render like any other run):

* **ground**: the plane ``z = 0`` with a tiling random texture (world ``(x, y)`` -> texel
  ``(x, y) / ground_texel_m``, period ``ground_texture_px * ground_texel_m``);
* **boxes**: crates, shelves and pillars standing on the ground beside the path (at least
  ``box_clearance_m`` from every path point, at most ``box_band_m``), four textured vertical
  faces and a textured top each, Lambertian shading from a fixed sun direction;
* **low-texture stretches**: everything within ``low_texture_radius_m`` of the path driven
  during the ``low_texture_s`` intervals has its texture contrast scaled by
  ``low_texture_contrast`` (a smooth material map over the ground; one factor per face);
  with ``low_texture_open`` no boxes stand there either;
* **sky**: a smooth gradient in the elevation of the viewing ray (no features).

Each textured plane maps to the image by a homography, so a face is drawn with one
``cv2.warpPerspective`` of its texture (mip level chosen from the texel footprint) over the
bounding box of its projection, clipped to the near plane, rasterised with
``cv2.fillConvexPoly``, and depth-tested on an inverse-depth buffer (inverse depth is affine in
the pixel coordinates on a plane). Image formation then applies, per frame and per the
weather condition in force (:mod:`msf_torch.sim.weather`):

* contrast ``c_mean / 0.10`` (snow cover lowers it);
* atmospheric scattering ``I = J t + A (1 - t)``, ``t = exp(-beta d)`` with ``d`` the range
  along the ray, ``beta`` from the condition's visibility and rain rate
  (:func:`~msf_torch.sim.weather.extinction_coefficient`), ``A`` the airlight; the sky has
  ``t = 0``;
* exposure and noise: a mid-grey pixel collects ``S = min(target, k E)`` electrons
  (:class:`~msf_torch.sim.weather.CameraModel`), shot noise ``sqrt(e)`` plus read noise;
  auto-exposure gain up to ``max_gain`` brings it back to mid-grey, beyond that (night) the
  image darkens;
* rain streaks (``rain_streaks_per_mm_h`` per frame per mm/h of rain) and snow flakes, drawn
  over the attenuated scene, then rounding to 8 bit.

Everything is deterministic: the scene from ``scene_seed``, each frame's noise and
precipitation from ``(seed, frame index, camera)``.

Example:
    >>> from msf_torch.sim.render import RunRenderer, render_sim_config
    >>> from msf_torch.sim import simulate_run
    >>> run = simulate_run(render_sim_config(duration_s=5.0), seed=0)
    >>> renderer = RunRenderer.for_run(run, seed=0)
    >>> frame = renderer.frame(0)
    >>> frame.left.shape, frame.left.dtype
    ((480, 640), dtype('uint8'))
"""

from __future__ import annotations

__all__ = [
    "SceneConfig",
    "Scene",
    "ImagingConfig",
    "FrameWeather",
    "StereoFrame",
    "RunRenderer",
    "build_scene",
    "mip_pyramid",
    "random_texture",
    "render_radiance",
    "expose",
    "render_sim_config",
    "loop_sim_config",
]

import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from scipy.spatial import cKDTree

from msf_torch.sensors.camera import CameraRig
from msf_torch.sim.weather import (
    DEFAULT_CONDITIONS,
    CameraModel,
    WeatherCondition,
    WeatherSchedule,
    extinction_coefficient,
)
from msf_torch.sim.wheeled import SimConfig, SimulatedRun

_MID_GREY = 128.0
_NEAR_M = 0.05


# --------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SceneConfig:
    """Layout and materials of a rendered scene.

    Attributes:
        box_density_per_m2: boxes per square metre of the band beside the path.
        box_clearance_m: least distance from any path point to a box's bounding circle, m.
        box_band_m: boxes lie at most this far from the path (centre distance), m.
        box_size_m: ``(low, high)`` side length range of the footprint, m.
        box_height_m: ``(low, high)`` height range, m.
        texture_count: number of random face textures.
        texture_px: side of a face texture, px (power of two).
        box_texel_m: texel size on faces, m.
        ground_texture_px: side of the ground texture, px (power of two).
        ground_texel_m: texel size on the ground, m.
        texture_contrast: standard deviation of the textures around mid-grey, DN.
        low_texture_s: path time intervals ``((t0, t1), ...)`` s whose surroundings are
            low-texture.
        low_texture_radius_m: radius around those path points, m.
        low_texture_contrast: contrast factor there (1 = unchanged).
        low_texture_open: no boxes there either (an open, featureless hall: only the dim
            floor and whatever lies beyond is left to track).
        sun_direction: direction towards the sun (world), for face shading.
        max_range_m: faces farther than this from the camera are not drawn, m.
    """

    box_density_per_m2: float = 0.06
    box_clearance_m: float = 1.2
    box_band_m: float = 25.0
    box_size_m: tuple[float, float] = (0.6, 2.5)
    box_height_m: tuple[float, float] = (1.2, 4.0)
    texture_count: int = 8
    texture_px: int = 512
    box_texel_m: float = 0.01
    ground_texture_px: int = 2048
    ground_texel_m: float = 0.02
    texture_contrast: float = 45.0
    low_texture_s: tuple[tuple[float, float], ...] = ()
    low_texture_radius_m: float = 8.0
    low_texture_contrast: float = 0.12
    low_texture_open: bool = False
    sun_direction: tuple[float, float, float] = (0.4, 0.3, 0.87)
    max_range_m: float = 80.0

    def validate(self) -> None:
        """Raise ``ValueError`` naming the field when a value is out of range."""
        for name in ("box_texel_m", "ground_texel_m", "max_range_m", "texture_contrast"):
            if not getattr(self, name) > 0:
                raise ValueError(f"SceneConfig.{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("texture_px", "ground_texture_px"):
            size = getattr(self, name)
            if size < 16 or size & (size - 1):
                raise ValueError(f"SceneConfig.{name} must be a power of two >= 16, got {size}")
        for name in ("box_size_m", "box_height_m"):
            low, high = getattr(self, name)
            if not 0 < low <= high:
                raise ValueError(f"SceneConfig.{name} must be 0 < low <= high, got {(low, high)}")
        if self.texture_count < 1 or self.box_density_per_m2 < 0:
            raise ValueError("SceneConfig: texture_count >= 1 and box_density_per_m2 >= 0")
        if not 0 <= self.low_texture_contrast <= 1:
            raise ValueError(
                f"SceneConfig.low_texture_contrast must lie in [0, 1], "
                f"got {self.low_texture_contrast}"
            )


@dataclass(frozen=True)
class ImagingConfig:
    """Image formation: airlight, exposure, noise, precipitation.

    Attributes:
        airlight: ``A`` of the scattering model, DN (the fog's brightness).
        sky_horizon, sky_zenith: sky brightness at the horizon and straight up, DN.
        camera: electrons per lux, auto-exposure target, read noise
            (:class:`~msf_torch.sim.weather.CameraModel`).
        max_gain: largest auto-exposure gain; a darker scene darkens the image.
        reference_contrast: the ``scene_contrast`` at which textures keep their contrast.
        rain_streaks_per_mm_h: rain streaks per frame per mm/h of rain rate.
        snow_flakes: flakes per frame in a ``"snow"`` condition.
    """

    airlight: float = 205.0
    sky_horizon: float = 200.0
    sky_zenith: float = 170.0
    camera: CameraModel = field(default_factory=CameraModel)
    max_gain: float = 4.0
    reference_contrast: float = 0.10
    rain_streaks_per_mm_h: float = 20.0
    snow_flakes: int = 250


@dataclass(frozen=True)
class FrameWeather:
    """Per-frame imaging quantities of one weather condition.

    Attributes:
        beta: extinction coefficient, 1/m.
        contrast: texture contrast factor.
        signal_electrons: ``S`` for a mid-grey pixel, e-.
        rain_rate_mm_h: rain rate, mm/h (streaks).
        snow: snowfall intensity, 0-1 (fraction of ``snow_flakes`` drawn).
        name: condition name.
    """

    beta: float = 0.0
    contrast: float = 1.0
    signal_electrons: float = 5000.0
    rain_rate_mm_h: float = 0.0
    snow: float = 0.0
    name: str = "clear"

    @classmethod
    def from_condition(cls, condition: WeatherCondition, imaging: ImagingConfig) -> FrameWeather:
        """The imaging quantities of a :class:`~msf_torch.sim.weather.WeatherCondition`."""
        beta = float(
            extinction_coefficient(condition.visibility_m, rain_rate_mm_h=condition.rain_rate_mm_h)
        )
        return cls(
            beta=beta,
            contrast=condition.scene_contrast / imaging.reference_contrast,
            signal_electrons=float(imaging.camera.signal_electrons(condition.illuminance_lux)),
            rain_rate_mm_h=condition.rain_rate_mm_h,
            snow=1.0 if condition.name == "snow" else 0.0,
            name=condition.name,
        )


def render_sim_config(**overrides: Any) -> SimConfig:
    """A :class:`~msf_torch.sim.wheeled.SimConfig` the renderer accepts: flat ground
    (``terrain_components = 0``), no GNSS outages unless given; ``overrides`` are further
    fields."""
    settings: dict[str, Any] = {"terrain_components": 0}
    settings.update(overrides)
    return SimConfig(**settings)


def loop_sim_config(radius_m: float = 15.0, **overrides: Any) -> SimConfig:
    """A flat-ground run that circles: mean heading rate ``v / radius`` with small turn and
    speed wiggles, so the path comes back near its start every ``2 pi radius / v`` seconds
    (loop sequences). ``overrides`` are further ``SimConfig`` fields."""
    speed = overrides.get("mean_speed_mps", SimConfig.mean_speed_mps)
    settings: dict[str, Any] = {
        "terrain_components": 0,
        "mean_turn_rate_rad_s": speed / radius_m,
        "turn_rate_peak_rad_s": 0.02,
        "speed_variation": 0.1,
    }
    settings.update(overrides)
    return SimConfig(**settings)


# --------------------------------------------------------------------------------------------
# Scene
# --------------------------------------------------------------------------------------------


@dataclass
class Scene:
    """A world-fixed textured scene.

    Faces are rectangles ``origin + a u + b v``, ``a, b in [0, 1]``, seen from the side of
    ``normal = (u x v) / |u x v|``.

    Attributes:
        face_origin, face_u, face_v, face_normal: (P, 3) world, m.
        face_texture: (P,) texture index.
        face_texel_offset: (P, 2) texel offset of the face's origin.
        face_contrast: (P,) contrast factor (low-texture stretches).
        face_shade: (P,) Lambertian brightness factor.
        textures: mip pyramids (level 0 first) of the face textures, uint8 (n, n).
        ground: mip pyramid of the ground texture, uint8.
        material: ground contrast-factor map, float32 (rows = y, cols = x).
        material_origin: world ``(x, y)`` of material cell ``(0, 0)``'s centre, m.
        material_cell_m: material map cell size, m.
        config: the :class:`SceneConfig`.
    """

    face_origin: np.ndarray
    face_u: np.ndarray
    face_v: np.ndarray
    face_normal: np.ndarray
    face_texture: np.ndarray
    face_texel_offset: np.ndarray
    face_contrast: np.ndarray
    face_shade: np.ndarray
    textures: list[list[np.ndarray]]
    ground: list[np.ndarray]
    material: np.ndarray
    material_origin: np.ndarray
    material_cell_m: float
    config: SceneConfig


def mip_pyramid(texture: np.ndarray, levels: int) -> list[np.ndarray]:
    """Mip levels of a uint8 texture (n, n): level 0 and up to ``levels - 1`` 2x2-box
    averages (a periodic texture stays periodic)."""
    out = [texture]
    current = texture.astype(np.float32)
    for _ in range(levels - 1):
        if min(current.shape) < 8:
            break
        current = 0.25 * (
            current[0::2, 0::2] + current[1::2, 0::2] + current[0::2, 1::2] + current[1::2, 1::2]
        )
        out.append(np.clip(current + 0.5, 0, 255).astype(np.uint8))
    return out


def random_texture(size: int, rng: np.random.Generator, contrast: float) -> np.ndarray:
    """A tileable random texture (size, size) uint8 around mid-grey, std ``contrast`` DN.

    Band-limited noise at octaves of 2 to 32 texels (periodic FFT filtering) plus random
    filled rectangles, discs and thick lines (drawn with wrap-around), whose corners and
    edges give the detector and tracker something to hold on to.
    """
    freq_y = np.fft.fftfreq(size)[:, None]
    freq_x = np.fft.rfftfreq(size)[None, :]
    radius2 = freq_y**2 + freq_x**2
    # one white spectrum shaped by the sum of the octaves' Gaussian filters, each octave
    # normalised to unit variance (the variance of filtered white noise is sum |G|^2)
    shaping = np.zeros_like(radius2)
    for scale in (2.0, 4.0, 8.0, 16.0, 32.0):
        sigma_f = 1.0 / (2.0 * math.pi * scale)
        gauss = np.exp(-0.5 * radius2 / sigma_f**2)
        shaping += math.sqrt(scale) * gauss / math.sqrt(float((gauss**2).sum()))
    white = np.fft.rfft2(rng.standard_normal((size, size)))
    noise = np.fft.irfft2(white * shaping, s=(size, size))
    noise /= noise.std()
    canvas = np.zeros((size, size), np.float32)
    shapes = int(size * size / 700)
    for _ in range(shapes):
        level = float(rng.uniform(-1.0, 1.0))
        kind = int(rng.integers(3))
        extent = float(math.exp(rng.uniform(math.log(4.0), math.log(0.08 * size))))
        x0, y0 = rng.uniform(0, size, 2)
        angle = float(rng.uniform(0, math.pi))
        wrap_x = [d for d in (-size, 0, size) if -extent <= x0 + d <= size + extent]
        wrap_y = [d for d in (-size, 0, size) if -extent <= y0 + d <= size + extent]
        for dx in wrap_x:
            for dy in wrap_y:
                cx, cy = x0 + dx, y0 + dy
                if kind == 0:
                    box = ((cx, cy), (extent, extent * rng.uniform(0.3, 1.0)), math.degrees(angle))
                    pts = cv2.boxPoints(box).astype(np.int32)
                    cv2.fillConvexPoly(canvas, pts, level)
                elif kind == 1:
                    cv2.circle(canvas, (int(cx), int(cy)), int(extent / 2) + 1, level, -1)
                else:
                    end = (
                        int(cx + extent * math.cos(angle)),
                        int(cy + extent * math.sin(angle)),
                    )
                    cv2.line(canvas, (int(cx), int(cy)), end, level, max(1, int(extent / 8)))
    combined = 0.6 * noise + 1.2 * canvas
    combined = (combined - combined.mean()) / combined.std()
    return np.clip(_MID_GREY + contrast * combined + 0.5, 0, 255).astype(np.uint8)


def _path_points(run: SimulatedRun, spacing_m: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Path times (N,) s and horizontal positions (N, 2) m, about ``spacing_m`` apart."""
    path = run.path
    length = path.mean_speed * (1.0 + float(np.abs(path.speed_amp).sum())) * path.duration_s
    count = max(2, int(math.ceil(length / spacing_m)) + 1)
    t = np.linspace(0.0, path.duration_s, count)
    return t, path.horizontal_position(t)


def build_scene(
    path_xy: np.ndarray,
    config: SceneConfig | None = None,
    seed: int = 0,
    low_texture_xy: np.ndarray | None = None,
) -> Scene:
    """Boxes beside a path and the ground, with textures; see the module docstring.

    Args:
        path_xy: (N, 2) horizontal path points, m (dense enough for the clearance test).
        config: layout and materials.
        seed: scene seed (layout, textures).
        low_texture_xy: (M, 2) path points whose surroundings are low-texture, m.
    Returns:
        :class:`Scene`.
    """
    config = config or SceneConfig()
    config.validate()
    path_xy = np.asarray(path_xy, np.float64).reshape(-1, 2)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7301]))
    cell = 1.0
    margin = config.box_band_m + config.max_range_m
    m_low = path_xy.min(0) - margin
    m_shape = np.ceil((path_xy.max(0) + margin - m_low) / cell).astype(int) + 1
    material = np.ones((m_shape[1], m_shape[0]), np.float32)
    if low_texture_xy is not None and len(low_texture_xy):
        gx = m_low[0] + cell * np.arange(m_shape[0])
        gy = m_low[1] + cell * np.arange(m_shape[1])
        grid = np.stack(np.meshgrid(gx, gy), -1).reshape(-1, 2)
        near, _ = cKDTree(np.asarray(low_texture_xy, np.float64).reshape(-1, 2)).query(grid)
        ramp = np.clip((near - config.low_texture_radius_m) / 5.0 + 0.5, 0.0, 1.0)
        factor = config.low_texture_contrast + (1.0 - config.low_texture_contrast) * ramp
        material = factor.reshape(m_shape[1], m_shape[0]).astype(np.float32)

    def contrast_at(xy: np.ndarray) -> np.ndarray:
        index = np.clip(np.rint((xy - m_low) / cell).astype(int), 0, m_shape - 1)
        return material[index[:, 1], index[:, 0]].astype(np.float64)

    tree = cKDTree(path_xy)
    low, high = path_xy.min(0) - config.box_band_m, path_xy.max(0) + config.box_band_m
    area = float(np.prod(high - low))
    candidates = rng.poisson(config.box_density_per_m2 * area)
    centre = rng.uniform(low, high, (candidates, 2))
    size = rng.uniform(*config.box_size_m, (candidates, 2))
    height = rng.uniform(*config.box_height_m, candidates)
    yaw = rng.uniform(-math.pi, math.pi, candidates)
    distance, _ = tree.query(centre)
    half_diagonal = 0.5 * np.linalg.norm(size, axis=-1)
    keep = (distance - half_diagonal >= config.box_clearance_m) & (distance <= config.box_band_m)
    if config.low_texture_open:
        keep &= contrast_at(centre) >= 1.0
    # boxes do not overlap one another (greedy, in draw order)
    chosen: list[int] = []
    for k in np.nonzero(keep)[0]:
        gaps = np.linalg.norm(centre[chosen] - centre[k], axis=-1) if chosen else np.zeros(0)
        if np.all(gaps > half_diagonal[chosen] + half_diagonal[k] + 0.1):
            chosen.append(int(k))
    idx = np.asarray(chosen, np.int64)
    centre, size, height, yaw = centre[idx], size[idx], height[idx], yaw[idx]

    origins, us, vs = [], [], []
    for (cx, cy), (sx, sy), h, psi in zip(centre, size, height, yaw, strict=True):
        ex = np.array([math.cos(psi), math.sin(psi), 0.0]) * sx
        ey = np.array([-math.sin(psi), math.cos(psi), 0.0]) * sy
        up = np.array([0.0, 0.0, h + 0.1])
        base = np.array([cx, cy, -0.1]) - 0.5 * ex - 0.5 * ey
        corners = [base, base + ex, base + ex + ey, base + ey]
        edges = [ex, ey, -ex, -ey]
        for corner, edge in zip(corners, edges, strict=True):
            origins.append(corner)
            us.append(edge)
            vs.append(up)  # u x up points out of the box for counter-clockwise edges
        origins.append(base + up)
        us.append(ex)
        vs.append(ey)
    face_origin = np.asarray(origins, np.float64).reshape(-1, 3)
    face_u = np.asarray(us, np.float64).reshape(-1, 3)
    face_v = np.asarray(vs, np.float64).reshape(-1, 3)
    normal = np.cross(face_u, face_v)
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
    count = face_origin.shape[0]
    face_texture = rng.integers(0, config.texture_count, count)
    face_offset = rng.uniform(0, config.texture_px, (count, 2))
    sun = np.asarray(config.sun_direction, np.float64)
    sun /= np.linalg.norm(sun)
    face_shade = 0.65 + 0.35 * np.clip(normal @ sun, 0.0, 1.0)

    levels = int(math.log2(config.texture_px)) - 2
    textures = [
        mip_pyramid(random_texture(config.texture_px, rng, config.texture_contrast), levels)
        for _ in range(config.texture_count)
    ]
    ground_levels = int(math.log2(config.ground_texture_px)) - 2
    ground = mip_pyramid(
        random_texture(config.ground_texture_px, rng, config.texture_contrast), ground_levels
    )

    face_contrast = contrast_at((face_origin + 0.5 * (face_u + face_v))[:, :2])
    return Scene(
        face_origin=face_origin,
        face_u=face_u,
        face_v=face_v,
        face_normal=normal,
        face_texture=face_texture,
        face_texel_offset=face_offset,
        face_contrast=face_contrast,
        face_shade=face_shade,
        textures=textures,
        ground=ground,
        material=material,
        material_origin=m_low,
        material_cell_m=cell,
        config=config,
    )


# --------------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------------


class _View:
    """One camera pose's projection helpers (pixel grid shared by all faces)."""

    def __init__(self, rig: CameraRig, centre: np.ndarray, rotation_wc: np.ndarray) -> None:
        self.rig = rig
        self.centre = centre
        self.rotation = rotation_wc  # camera -> world
        self.k = rig.matrix()
        self.k_inv = np.linalg.inv(self.k)

    def image_to_plane(
        self, normal: np.ndarray, offset: float, linear: np.ndarray, shift: np.ndarray
    ) -> np.ndarray:
        """Homography (3, 3) from pixels to the plane coordinates ``linear @ X + shift``
        of the plane ``normal . X = offset`` (world)."""
        centre = self.centre
        top = (
            linear @ centre[:, None] @ normal[None, :]
            + (offset - normal @ centre) * linear
            + shift[:, None] @ normal[None, :]
        )
        return np.vstack((top, normal[None, :])) @ self.rotation @ self.k_inv

    def inverse_depth_plane(self, normal: np.ndarray, offset: float) -> np.ndarray:
        """Coefficients (3,) ``g`` with inverse depth ``1 / z = g . [u, v, 1]`` on the plane."""
        return (normal @ self.rotation @ self.k_inv) / (offset - normal @ self.centre)


def _clip_near(points: np.ndarray) -> np.ndarray:
    """Clip a convex polygon (V, 3) in camera coordinates to ``z >= _NEAR_M``."""
    out = []
    count = len(points)
    for i in range(count):
        a, b = points[i], points[(i + 1) % count]
        a_in, b_in = a[2] >= _NEAR_M, b[2] >= _NEAR_M
        if a_in:
            out.append(a)
        if a_in != b_in:
            s = (_NEAR_M - a[2]) / (b[2] - a[2])
            out.append(a + s * (b - a))
    return np.asarray(out).reshape(-1, 3)


def _mip_level(depth: float, slant: float, texel_m: float, fx: float, levels: int) -> int:
    """Mip level for a pixel footprint ``depth / (fx sqrt(slant))`` m on texels of
    ``texel_m``."""
    footprint = depth / (fx * math.sqrt(max(slant, 1e-3))) / texel_m
    return int(np.clip(math.floor(math.log2(max(footprint, 1e-9)) + 0.5), 0, levels - 1))


def _level_homography(image_to_texel: np.ndarray, level: int, x0: int, y0: int) -> np.ndarray:
    """Homography from ROI pixels (origin ``(x0, y0)``) to texels of mip ``level``."""
    scale = 0.5**level
    to_level = np.array(
        [[scale, 0.0, 0.5 * scale - 0.5], [0.0, scale, 0.5 * scale - 0.5], [0.0, 0.0, 1.0]]
    )
    shift = np.array([[1.0, 0.0, x0], [0.0, 1.0, y0], [0.0, 0.0, 1.0]])
    return to_level @ image_to_texel @ shift


def _warp(texture: np.ndarray, homography: np.ndarray, width: int, height: int) -> np.ndarray:
    return cv2.warpPerspective(
        texture,
        homography,
        (width, height),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_WRAP,
    )


def _draw_ground(
    scene: Scene,
    view: _View,
    radiance: np.ndarray,
    inverse_depth: np.ndarray,
    ray_norm: np.ndarray,
) -> None:
    """Draw the plane ``z = 0`` (seen from above) into the buffers."""
    rig = view.rig
    up = np.array([0.0, 0.0, 1.0])
    if view.centre[2] <= 0.0:
        return
    coeff = view.inverse_depth_plane(up, 0.0)
    inv = _affine_image(coeff, rig.width, rig.height)
    visible = inv > 1.0 / scene.config.max_range_m
    if not visible.any():
        return
    rows = np.nonzero(visible.any(1))[0]
    y0, y1 = int(rows[0]), int(rows[-1]) + 1
    texel = scene.config.ground_texel_m
    to_texel = view.image_to_plane(up, 0.0, np.eye(2, 3) / texel, np.zeros(2))
    inv_band = np.maximum(inv[y0:y1], 1e-9)
    # range along the ray and cosine of incidence |n . r| / |r| = height * (1 / z) / |r|
    distance = ray_norm[y0:y1] / inv_band
    slant = view.centre[2] * inv_band / ray_norm[y0:y1]
    footprint = distance / (rig.fx * np.sqrt(np.clip(slant, 1e-3, 1.0))) / texel
    levels = len(scene.ground)
    level = np.clip(np.floor(np.log2(np.maximum(footprint, 1e-9)) + 0.5), 0, levels - 1)
    level = level.astype(np.int8)
    band = np.zeros((y1 - y0, rig.width), np.float32)
    shown = level[visible[y0:y1]]
    for lev in range(int(shown.min()), int(shown.max()) + 1):
        sel = (level == lev) & visible[y0:y1]
        sel_rows = np.nonzero(sel.any(1))[0]
        if not sel_rows.size:
            continue
        r0, r1 = int(sel_rows[0]), int(sel_rows[-1]) + 1
        patch = _warp(
            scene.ground[int(lev)],
            _level_homography(to_texel, int(lev), 0, y0 + r0),
            rig.width,
            r1 - r0,
        )
        np.copyto(band[r0:r1], patch, where=sel[r0:r1], casting="unsafe")
    cell = scene.material_cell_m
    to_material = view.image_to_plane(
        up, 0.0, np.eye(2, 3) / cell, -scene.material_origin / cell
    ) @ np.array([[1.0, 0, 0], [0, 1.0, y0], [0, 0, 1.0]])
    contrast = cv2.warpPerspective(
        scene.material,
        to_material,
        (rig.width, y1 - y0),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REPLICATE,
    )
    shaded = _MID_GREY + (band - _MID_GREY) * contrast
    sel = visible[y0:y1]
    np.copyto(radiance[y0:y1], shaded, where=sel)
    np.copyto(inverse_depth[y0:y1], inv[y0:y1], where=sel)


def _draw_faces(scene: Scene, view: _View, radiance: np.ndarray, inverse_depth: np.ndarray) -> None:
    """Draw the boxes' faces (back faces and far faces culled) with a depth test."""
    rig = view.rig
    centre = view.centre
    config = scene.config
    to_camera = view.rotation.T
    facing = np.einsum("pi,pi->p", scene.face_normal, centre - scene.face_origin) > 1e-6
    mid = scene.face_origin + 0.5 * (scene.face_u + scene.face_v)
    reach = 0.5 * np.linalg.norm(scene.face_u + scene.face_v, axis=-1)
    near = np.linalg.norm(mid - centre, axis=-1) - reach < config.max_range_m
    corners = np.stack(
        (
            scene.face_origin,
            scene.face_origin + scene.face_u,
            scene.face_origin + scene.face_u + scene.face_v,
            scene.face_origin + scene.face_v,
        ),
        1,
    )  # (P, 4, 3)
    cam = (corners - centre) @ to_camera.T  # (P, 4, 3)
    depth = cam[..., 2]
    ahead = (depth > _NEAR_M).any(-1)
    in_front = (depth >= _NEAR_M).all(-1)
    width, height = rig.width, rig.height
    safe = np.where(in_front[:, None], depth, 1.0)
    u = rig.fx * cam[..., 0] / safe + rig.cx
    v = rig.fy * cam[..., 1] / safe + rig.cy
    overlaps = (u.max(-1) >= 0) & (u.min(-1) < width) & (v.max(-1) >= 0) & (v.min(-1) < height)
    candidates = np.nonzero(facing & near & ahead & (overlaps | ~in_front))[0]
    for p in candidates:
        if in_front[p]:
            poly = cam[p]
            uv = np.stack((u[p], v[p]), -1)
        else:
            poly = _clip_near(cam[p])
            if len(poly) < 3:
                continue
            uv = rig.project(poly)
        x0 = max(int(math.floor(uv[:, 0].min())), 0)
        x1 = min(int(math.ceil(uv[:, 0].max())) + 1, width)
        y0 = max(int(math.floor(uv[:, 1].min())), 0)
        y1 = min(int(math.ceil(uv[:, 1].max())) + 1, height)
        if x1 <= x0 or y1 <= y0:
            continue
        normal = scene.face_normal[p]
        offset = float(normal @ scene.face_origin[p])
        coeff = view.inverse_depth_plane(normal, offset)
        xs = np.arange(x0, x1, dtype=np.float64)
        ys = np.arange(y0, y1, dtype=np.float64)
        inv = (coeff[0] * xs[None, :] + coeff[1] * ys[:, None] + coeff[2]).astype(np.float32)
        mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
        shift = 4
        pts = np.rint((uv - [x0, y0]) * (1 << shift)).astype(np.int32)
        cv2.fillConvexPoly(mask, pts, 1, cv2.LINE_8, shift)
        mask = mask.astype(bool) & (inv > inverse_depth[y0:y1, x0:x1])
        if not mask.any():
            continue
        u_hat = scene.face_u[p] / np.linalg.norm(scene.face_u[p])
        v_hat = scene.face_v[p] / np.linalg.norm(scene.face_v[p])
        texel = config.box_texel_m
        linear = np.stack((u_hat, v_hat)) / texel
        shift_t = scene.face_texel_offset[p] - linear @ scene.face_origin[p]
        to_texel = view.image_to_plane(normal, offset, linear, shift_t)
        depth_min = float(poly[:, 2].min())
        depth_max = float(poly[:, 2].max())
        view_dir = mid[p] - centre
        slant = abs(float(normal @ view_dir)) / max(float(np.linalg.norm(view_dir)), 1e-9)
        pyramid = scene.textures[int(scene.face_texture[p])]
        level = _mip_level(math.sqrt(depth_min * depth_max), slant, texel, rig.fx, len(pyramid))
        patch = _warp(
            pyramid[level], _level_homography(to_texel, level, x0, y0), x1 - x0, y1 - y0
        ).astype(np.float32)
        gain = scene.face_shade[p]
        patch = gain * (_MID_GREY + (patch - _MID_GREY) * scene.face_contrast[p])
        np.copyto(radiance[y0:y1, x0:x1], patch, where=mask)
        np.copyto(inverse_depth[y0:y1, x0:x1], inv, where=mask)


def _affine_image(coeff: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) float32 image of ``coeff . [u, v, 1]`` over the pixel grid."""
    u = np.arange(width, dtype=np.float32) * np.float32(coeff[0])
    v = np.arange(height, dtype=np.float32) * np.float32(coeff[1]) + np.float32(coeff[2])
    return v[:, None] + u[None, :]


_RAY_NORMS: dict[CameraRig, np.ndarray] = {}


def _ray_norm(rig: CameraRig) -> np.ndarray:
    """(H, W) float32 ``|K^-1 [u, v, 1]|`` (range = depth times this), cached per rig."""
    if rig not in _RAY_NORMS:
        u = (np.arange(rig.width) - rig.cx) / rig.fx
        v = (np.arange(rig.height) - rig.cy) / rig.fy
        norm = np.sqrt(u[None, :] ** 2 + v[:, None] ** 2 + 1.0)
        _RAY_NORMS[rig] = norm.astype(np.float32)
    return _RAY_NORMS[rig]


def render_radiance(
    scene: Scene,
    rig: CameraRig,
    centre: np.ndarray,
    rotation_wc: np.ndarray,
    imaging: ImagingConfig | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Scene radiance (before weather, noise and contrast) and range seen by one camera.

    Args:
        scene: the scene.
        rig: intrinsics and image size.
        centre: (3,) camera centre in the world, m.
        rotation_wc: (3, 3) camera -> world rotation.
        imaging: sky brightness.
    Returns:
        radiance (H, W) float32 DN-equivalent (mid-grey 128) and range (H, W) float32 m
        along each pixel's ray (``inf`` for the sky).
    """
    imaging = imaging or ImagingConfig()
    centre = np.asarray(centre, np.float64)
    rotation_wc = np.asarray(rotation_wc, np.float64)
    view = _View(rig, centre, rotation_wc)
    ray_norm = _ray_norm(rig)
    radiance = np.zeros((rig.height, rig.width), np.float32)
    inverse_depth = np.zeros((rig.height, rig.width), np.float32)
    _draw_ground(scene, view, radiance, inverse_depth, ray_norm)
    _draw_faces(scene, view, radiance, inverse_depth)
    sky = inverse_depth <= 0.0
    if sky.any():
        elevation = _affine_image(rotation_wc[2] @ view.k_inv, rig.width, rig.height) / ray_norm
        sky_value = imaging.sky_horizon + (imaging.sky_zenith - imaging.sky_horizon) * np.clip(
            elevation, 0.0, 1.0
        )
        np.copyto(radiance, sky_value, where=sky)
    with np.errstate(divide="ignore"):
        distance = ray_norm / inverse_depth
    distance[sky] = np.inf
    return radiance, distance


def expose(
    radiance: np.ndarray,
    distance: np.ndarray,
    weather: FrameWeather,
    rng: np.random.Generator,
    imaging: ImagingConfig | None = None,
) -> np.ndarray:
    """Form the 8-bit image of a radiance map under ``weather`` (see the module docstring).

    Args:
        radiance: (H, W) float32 DN-equivalent radiance (mid-grey 128).
        distance: (H, W) float32 range, m (``inf`` for the sky).
        weather: the frame's imaging quantities.
        rng: noise and precipitation stream.
        imaging: airlight, exposure, precipitation settings.
    Returns:
        (H, W) uint8 image.
    """
    imaging = imaging or ImagingConfig()
    scene_px = np.isfinite(distance)
    value = radiance.astype(np.float32, copy=True)
    if weather.contrast != 1.0:
        value[scene_px] = _MID_GREY + (value[scene_px] - _MID_GREY) * weather.contrast
    if weather.beta > 0.0:
        transmission = np.exp(-np.float32(weather.beta) * np.where(scene_px, distance, 0.0))
        transmission[~scene_px] = 0.0
        value = value * transmission + imaging.airlight * (1.0 - transmission)
    value = np.maximum(value, 0.0)
    target = imaging.camera.target_signal_electrons
    signal = weather.signal_electrons
    gain = min(imaging.max_gain, target / max(signal, 1e-9))
    electrons = value * (signal / _MID_GREY)
    read = imaging.camera.read_noise_electrons
    noise = rng.standard_normal(value.shape, dtype=np.float32)
    electrons = electrons + noise * np.sqrt(electrons + read * read)
    image = electrons * np.float32(gain * _MID_GREY / target)
    height, width = image.shape
    if weather.rain_rate_mm_h > 0.0:
        count = rng.poisson(imaging.rain_streaks_per_mm_h * weather.rain_rate_mm_h)
        layer = np.zeros((height, width), np.uint8)
        slant = math.radians(float(rng.normal(8.0, 2.0)))
        for _ in range(count):
            x, y = rng.uniform(0, width), rng.uniform(-40, height)
            length = rng.uniform(12.0, 45.0)
            end = (int(x + length * math.sin(slant)), int(y + length * math.cos(slant)))
            cv2.line(layer, (int(x), int(y)), end, int(rng.uniform(40, 110)), 1, cv2.LINE_AA)
        alpha = layer.astype(np.float32) / 255.0
        image = image * (1.0 - alpha) + 235.0 * alpha
    if weather.snow > 0.0:
        layer = np.zeros((height, width), np.uint8)
        for _ in range(int(round(weather.snow * imaging.snow_flakes))):
            centre = (int(rng.uniform(0, width)), int(rng.uniform(0, height)))
            cv2.circle(layer, centre, int(rng.integers(1, 4)), int(rng.uniform(120, 230)), -1)
        alpha = layer.astype(np.float32) / 255.0
        image = image * (1.0 - alpha) + 240.0 * alpha
    return np.clip(image + 0.5, 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------------------------
# Runs
# --------------------------------------------------------------------------------------------


@dataclass
class StereoFrame:
    """One rendered stereo frame and its truth.

    Attributes:
        index: frame index.
        t: time, s.
        left, right: (H, W) uint8 images (``right`` None for a monocular rig).
        position: (3,) body position, world, m.
        rotation: (3, 3) body -> world.
        weather: the frame's imaging quantities.
    """

    index: int
    t: float
    left: np.ndarray
    right: np.ndarray | None
    position: np.ndarray
    rotation: np.ndarray
    weather: FrameWeather


class RunRenderer:
    """Renders the frames of a simulated run on demand (deterministic, nothing cached).

    Args:
        run: the simulated run (flat ground: ``terrain_components = 0``).
        scene: its scene.
        rig: the stereo rig.
        rate_hz: frame rate, Hz; frames at ``k / rate_hz`` within the run.
        seed: per-frame noise seed.
        schedule: weather schedule (None: ``"sunny"`` throughout).
        conditions: name -> condition.
        imaging: image formation settings.
        stereo: render the right image too.
        transition_s: weather changes are blended over this long around each schedule
            boundary, s.
    Raises:
        ValueError: the run's ground is not flat.
    """

    def __init__(
        self,
        run: SimulatedRun,
        scene: Scene,
        rig: CameraRig | None = None,
        rate_hz: float = 10.0,
        seed: int = 0,
        schedule: WeatherSchedule | None = None,
        conditions: dict[str, WeatherCondition] | None = None,
        imaging: ImagingConfig | None = None,
        stereo: bool = True,
        transition_s: float = 4.0,
    ) -> None:
        if run.path.terrain_amp.size and float(np.abs(run.path.terrain_amp).max()) > 0.0:
            raise ValueError(
                "RunRenderer: the scene's ground is the plane z = 0; simulate the run with "
                "terrain_components = 0 (render_sim_config / loop_sim_config)"
            )
        if rate_hz <= 0:
            raise ValueError(f"RunRenderer: rate_hz must be > 0, got {rate_hz}")
        self.run = run
        self.scene = scene
        self.rig = rig or CameraRig()
        self.rate_hz = float(rate_hz)
        self.seed = int(seed)
        self.schedule = schedule
        self.conditions = dict(conditions or DEFAULT_CONDITIONS)
        self.imaging = imaging or ImagingConfig()
        self.stereo = stereo
        self.transition_s = float(transition_s)
        count = int(math.floor(run.path.duration_s * self.rate_hz + 1e-9)) + 1
        self.times = np.arange(count) / self.rate_hz
        self._weather = self._frame_weather()

    @classmethod
    def for_run(
        cls,
        run: SimulatedRun,
        scene_config: SceneConfig | None = None,
        scene_seed: int | None = None,
        **kwargs: Any,
    ) -> RunRenderer:
        """Build the run's scene (boxes along its path, low-texture stretches from
        ``scene_config.low_texture_s``) and a renderer; ``kwargs`` go to the constructor."""
        scene_config = scene_config or SceneConfig()
        t, xy = _path_points(run)
        low = np.zeros((0, 2))
        for start, end in scene_config.low_texture_s:
            inside = (t >= start) & (t <= end)
            low = np.concatenate((low, xy[inside]), 0)
        seed = kwargs.get("seed", 0) if scene_seed is None else scene_seed
        scene = build_scene(xy, scene_config, seed=seed, low_texture_xy=low)
        return cls(run, scene, **kwargs)

    def _frame_weather(self) -> list[FrameWeather]:
        """Per-frame weather: each schedule segment's quantities, blended linearly over
        ``transition_s`` centred on every boundary (weather and auto-exposure change
        gradually; the labels keep the schedule's boundaries). The signal is blended in
        log space."""
        if self.schedule is None:
            sunny = FrameWeather.from_condition(self.conditions["sunny"], self.imaging)
            return [sunny] * len(self.times)
        segments = self.schedule.segments
        per_segment = [
            FrameWeather.from_condition(self.conditions[seg.condition], self.imaging)
            for seg in segments
        ]
        half = 0.5 * max(self.transition_s, 1e-9)
        weights = np.ones((len(self.times), len(segments)))
        for j, seg in enumerate(segments):
            if j > 0:
                weights[:, j] *= np.clip((self.times - seg.t_start + half) / (2 * half), 0, 1)
            if j < len(segments) - 1:
                weights[:, j] *= np.clip((seg.t_end + half - self.times) / (2 * half), 0, 1)
        weights /= weights.sum(1, keepdims=True)

        def blend(values: list[float], row: np.ndarray) -> float:
            return float(row @ np.asarray(values))

        out = []
        for row in weights:
            main = int(np.argmax(row))
            out.append(
                FrameWeather(
                    beta=blend([w.beta for w in per_segment], row),
                    contrast=blend([w.contrast for w in per_segment], row),
                    signal_electrons=math.exp(
                        blend([math.log(w.signal_electrons) for w in per_segment], row)
                    ),
                    rain_rate_mm_h=blend([w.rain_rate_mm_h for w in per_segment], row),
                    snow=blend([w.snow for w in per_segment], row),
                    name=per_segment[main].name,
                )
            )
        return out

    def __len__(self) -> int:
        return len(self.times)

    def __iter__(self) -> Iterator[StereoFrame]:
        for k in range(len(self)):
            yield self.frame(k)

    def body_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """Truth at the frame times: positions (F, 3) m, rotations (F, 3, 3) body -> world."""
        state = self.run.path.evaluate(self.times)
        return state.position, state.rotation

    def camera_pose(
        self, position: np.ndarray, rotation: np.ndarray, right: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """Camera centre (3,) and camera -> world rotation (3, 3) of a body pose."""
        centre = position + rotation @ self.rig.body_translation_cam(right)
        return centre, rotation @ self.rig.body_rotation_cam()

    def true_disparity(self, position: np.ndarray, rotation: np.ndarray) -> np.ndarray:
        """The left camera's true stereo disparity ``fx b / z`` (H, W) px at a body pose
        (position (3,) m, body -> world rotation (3, 3)), from the rendered ranges; 0 where
        the ray meets nothing. A reference for stereo matching (e.g. a frame's
        ``position`` / ``rotation``)."""
        rig = self.rig
        centre, rotation_wc = self.camera_pose(position, rotation)
        _, distance = render_radiance(self.scene, rig, centre, rotation_wc, self.imaging)
        u = (np.arange(rig.width) - rig.cx) / rig.fx
        v = (np.arange(rig.height) - rig.cy) / rig.fy
        ray_norm = np.sqrt(u[None, :] ** 2 + v[:, None] ** 2 + 1.0)
        return rig.fx * rig.baseline_m * ray_norm / distance

    def frame(self, index: int, weather: FrameWeather | None = None) -> StereoFrame:
        """Render frame ``index`` (``weather`` overrides the schedule's)."""
        if not 0 <= index < len(self):
            raise IndexError(f"frame {index} outside 0..{len(self) - 1}")
        t = float(self.times[index])
        state = self.run.path.evaluate(np.array([t]))
        position, rotation = state.position[0], state.rotation[0]
        weather = weather or self._weather[index]
        images = []
        for camera in range(2 if self.stereo else 1):
            centre, rotation_wc = self.camera_pose(position, rotation, right=camera == 1)
            radiance, distance = render_radiance(
                self.scene, self.rig, centre, rotation_wc, self.imaging
            )
            rng = np.random.default_rng(np.random.SeedSequence([self.seed, index, camera]))
            images.append(expose(radiance, distance, weather, rng, self.imaging))
        return StereoFrame(
            index=index,
            t=t,
            left=images[0],
            right=images[1] if self.stereo else None,
            position=position,
            rotation=rotation,
            weather=weather,
        )
