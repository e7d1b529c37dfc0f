"""Rendered stereo images: projection against the closed-form pinhole, stereo disparity,
scattering formula, determinism, weather blending, low-texture stretches."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from msf_torch.sensors.camera import CameraRig
from msf_torch.sim import SimConfig, simulate_run
from msf_torch.sim.render import (
    FrameWeather,
    ImagingConfig,
    RunRenderer,
    SceneConfig,
    build_scene,
    expose,
    loop_sim_config,
    mip_pyramid,
    render_radiance,
    render_sim_config,
)
from msf_torch.sim.weather import CameraModel, WeatherSchedule

SMALL = SceneConfig(texture_count=2, texture_px=256, ground_texture_px=256, box_density_per_m2=0.0)


def marker_scene(marker_texel: tuple[int, int], texel_m: float = 0.01):
    """One 2 m x 2 m vertical face at x = 3 m facing -x (towards the origin), black with a
    4 x 4-texel white marker whose first texel is ``marker_texel``; returns the scene and
    the marker centre (world, m)."""
    scene = build_scene(np.zeros((2, 2)), dataclasses.replace(SMALL, box_texel_m=texel_m))
    size = 256
    texture = np.zeros((size, size), np.uint8)
    i, j = marker_texel
    texture[j : j + 4, i : i + 4] = 255
    origin = np.array([3.0, 1.0, 0.0])
    u = np.array([0.0, -2.0, 0.0])  # towards -y
    v = np.array([0.0, 0.0, 2.0])  # up; u x v = -4 x: faces the origin
    normal = np.cross(u, v) / np.linalg.norm(np.cross(u, v))
    scene = dataclasses.replace(
        scene,
        face_origin=origin[None],
        face_u=u[None],
        face_v=v[None],
        face_normal=normal[None],
        face_texture=np.zeros(1, np.int64),
        face_texel_offset=np.zeros((1, 2)),
        face_contrast=np.ones(1),
        face_shade=np.ones(1),
        textures=[mip_pyramid(texture, 4)],
    )
    centre_texel = np.array([i + 1.5, j + 1.5])
    marker = origin + centre_texel[0] * texel_m * u / 2.0 + centre_texel[1] * texel_m * v / 2.0
    return scene, marker


def camera_looking_along_x(rig: CameraRig, right: bool = False):
    """Camera centre and camera -> world rotation of a level body at (0, 0, 0)."""
    body_rotation = np.eye(3)
    centre = body_rotation @ rig.body_translation_cam(right)
    return centre, body_rotation @ rig.body_rotation_cam()


def blob_centroid(image: np.ndarray, around: np.ndarray, half: int = 8) -> np.ndarray:
    x0, y0 = (np.rint(around) - half).astype(int)
    window = image[y0 : y0 + 2 * half + 1, x0 : x0 + 2 * half + 1].astype(np.float64)
    window = np.where(window > 1.0, window, 0.0)
    ys, xs = np.mgrid[0 : window.shape[0], 0 : window.shape[1]]
    total = window.sum()
    return np.array([(xs * window).sum() / total + x0, (ys * window).sum() / total + y0])


@pytest.mark.parametrize("marker_texel", [(60, 70), (120, 110), (30, 140)])
def test_marker_projects_to_the_closed_form_pixel(marker_texel):
    rig = CameraRig()
    scene, marker = marker_scene(marker_texel)
    for right in (False, True):
        centre, rotation_wc = camera_looking_along_x(rig, right)
        radiance, distance = render_radiance(scene, rig, centre, rotation_wc)
        cam = rotation_wc.T @ (marker - centre)
        expected = np.array([rig.fx * cam[0] / cam[2] + rig.cx, rig.fy * cam[1] / cam[2] + rig.cy])
        found = blob_centroid(radiance, expected)
        assert np.abs(found - expected).max() < 0.1, (right, found, expected)
        # the range there is the closed-form distance to the face along the pixel's ray
        px = np.rint(expected).astype(int)
        ray = np.linalg.inv(rig.matrix()) @ np.array([px[0], px[1], 1.0])
        ray_world = rotation_wc @ ray
        expected_range = (3.0 - centre[0]) / ray_world[0] * np.linalg.norm(ray)
        assert abs(distance[px[1], px[0]] - expected_range) < 1e-4 * expected_range


def test_stereo_disparity_is_fx_baseline_over_depth():
    rig = CameraRig()
    scene, marker = marker_scene((100, 100))
    found = []
    for right in (False, True):
        centre, rotation_wc = camera_looking_along_x(rig, right)
        radiance, _ = render_radiance(scene, rig, centre, rotation_wc)
        cam = rotation_wc.T @ (marker - centre)
        guess = rig.project(cam)
        found.append(blob_centroid(radiance, guess))
        depth = cam[2]
    disparity = found[0][0] - found[1][0]
    assert disparity == pytest.approx(rig.fx * rig.baseline_m / depth, abs=0.1)
    assert abs(found[0][1] - found[1][1]) < 0.05  # rectified: same row


def test_scattering_formula_and_noise_free_exposure():
    rig = CameraRig()
    scene = build_scene(
        np.array([[0.0, 0.0], [10.0, 0.0]]),
        dataclasses.replace(SMALL, box_density_per_m2=0.05),
        seed=3,
    )
    centre, rotation_wc = camera_looking_along_x(rig)
    radiance, distance = render_radiance(scene, rig, centre, rotation_wc)
    assert np.isinf(distance[0]).any() and np.isfinite(distance[-1]).all()  # sky, ground
    camera = CameraModel(target_signal_electrons=1e12, read_noise_electrons=0.0)
    imaging = ImagingConfig(camera=camera)
    rng = np.random.default_rng(0)
    beta = 0.05
    weather = FrameWeather(beta=beta, signal_electrons=1e12)
    image = expose(radiance, distance, weather, rng, imaging).astype(np.float64)
    t = np.exp(-beta * np.where(np.isfinite(distance), distance, np.inf))
    expected = radiance * t + imaging.airlight * (1.0 - t)
    assert np.abs(image - np.clip(expected, 0, 255)).max() <= 0.5 + 1e-3


def test_frames_are_deterministic_and_seeded():
    run = simulate_run(render_sim_config(duration_s=2.0), seed=4)
    a = RunRenderer.for_run(run, SMALL, seed=5).frame(3)
    b = RunRenderer.for_run(run, SMALL, seed=5).frame(3)
    c = RunRenderer.for_run(run, SMALL, seed=6, scene_seed=5).frame(3)
    assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
    # same scene, other noise: small differences only
    diff = np.abs(a.left.astype(int) - c.left.astype(int))
    assert 0 < diff.mean() < 5.0
    position, rotation = RunRenderer.for_run(run, SMALL, seed=5).body_poses()
    assert np.allclose(position[3], a.position) and np.allclose(rotation[3], a.rotation)


def test_weather_blends_over_the_transition():
    run = simulate_run(render_sim_config(duration_s=20.0), seed=1)
    schedule = WeatherSchedule.from_boundaries([0.0, 10.0, 20.0], ["sunny", "fog"])
    renderer = RunRenderer.for_run(run, SMALL, schedule=schedule, transition_s=4.0)
    beta = np.array([w.beta for w in renderer._weather])
    t = renderer.times
    sunny, fog = beta[0], beta[-1]
    assert fog > 100 * sunny
    assert np.allclose(beta[t <= 8.0], sunny) and np.allclose(beta[t >= 12.0], fog)
    assert beta[t == 10.0][0] == pytest.approx(0.5 * (sunny + fog))
    assert np.all(np.diff(beta) >= -1e-15)


def test_low_texture_stretch_lowers_contrast():
    run = simulate_run(loop_sim_config(duration_s=30.0), seed=2)
    config = dataclasses.replace(SMALL, box_density_per_m2=0.06, low_texture_s=((15.0, 25.0),))
    renderer = RunRenderer.for_run(run, config, seed=0)
    assert renderer.scene.face_contrast.min() == pytest.approx(config.low_texture_contrast)
    inside = renderer.frame(int(20.0 * renderer.rate_hz)).left
    outside = renderer.frame(int(5.0 * renderer.rate_hz)).left
    lower = inside[240:].astype(float).std()  # the ground half
    assert lower < 0.4 * outside[240:].astype(float).std()


def test_rejects_non_flat_ground():
    run = simulate_run(SimConfig(duration_s=2.0), seed=0)
    with pytest.raises(ValueError, match="terrain_components = 0"):
        RunRenderer.for_run(run, SMALL)
    flat = simulate_run(render_sim_config(duration_s=2.0), seed=0)
    assert math.isfinite(RunRenderer.for_run(flat, SMALL).times[-1])


def test_loop_run_revisits_the_same_view():
    """The scene is world-fixed: where a loop run comes back (within 0.5 m and 10 deg), the
    image matches the first pass far better than one taken half a loop later."""
    run = simulate_run(loop_sim_config(duration_s=80.0), seed=1)
    renderer = RunRenderer.for_run(run, SMALL, seed=0)
    position, rotation = renderer.body_poses()
    yaw = np.arctan2(rotation[:, 1, 0], rotation[:, 0, 0])
    first, later = np.arange(0, 200), np.arange(500, len(position))
    gap = np.linalg.norm(position[first, None, :2] - position[None, later, :2], axis=-1)
    turn = np.abs(np.angle(np.exp(1j * (yaw[first, None] - yaw[None, later]))))
    gap[turn > np.radians(10.0)] = np.inf
    i, j = np.unravel_index(np.argmin(gap), gap.shape)
    assert gap[i, j] < 0.5
    a, b = (renderer.frame(int(k)).left.astype(float) for k in (first[i], later[j]))
    other = renderer.frame(int(first[i] + later[j]) // 2).left.astype(float)

    def ncc(x: np.ndarray, y: np.ndarray) -> float:
        return float(((x - x.mean()) * (y - y.mean())).mean() / (x.std() * y.std()))

    assert ncc(a, b) > ncc(a, other) + 0.1
