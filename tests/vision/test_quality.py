"""Image-quality statistics: hand-computed values, and fog statistics against the extinction
coefficient of rendered scattering."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from msf_torch.sensors.camera import CameraRig
from msf_torch.sim.render import (
    FrameWeather,
    ImagingConfig,
    SceneConfig,
    build_scene,
    expose,
    render_radiance,
)
from msf_torch.sim.weather import CameraModel
from msf_torch.vision.quality import QUALITY_NAMES, image_quality

IMAGE = np.array(
    [
        [10, 20, 30, 40, 50],
        [60, 70, 80, 90, 100],
        [15, 25, 35, 45, 55],
        [200, 210, 220, 230, 240],
    ],
    np.uint8,
)


def test_statistics_by_hand():
    values = IMAGE.astype(float)
    rows, cols = values.shape
    mean = values.sum() / values.size
    std = np.sqrt(((values - mean) ** 2).sum() / values.size)
    laplacian = [
        values[r - 1, c] + values[r + 1, c] + values[r, c - 1] + values[r, c + 1] - 4 * values[r, c]
        for r in range(1, rows - 1)
        for c in range(1, cols - 1)
    ]
    lap_mean = sum(laplacian) / len(laplacian)
    lap_var = sum((x - lap_mean) ** 2 for x in laplacian) / len(laplacian)
    dark = np.empty_like(values)
    for r in range(rows):
        for c in range(cols):
            window = [
                values[min(max(r + dr, 0), rows - 1), min(max(c + dc, 0), cols - 1)]
                for dr in (-1, 0, 1)
                for dc in (-1, 0, 1)
            ]
            dark[r, c] = min(window)
    fog = dark.mean() / dark.max()  # 20 pixels: the brightest 0.1 % is the single maximum
    stats = dict(zip(QUALITY_NAMES, image_quality(IMAGE, patch=3), strict=True))
    assert stats["contrast"] == pytest.approx(std / 255.0, rel=1e-6)
    assert stats["brightness"] == pytest.approx(mean / 255.0, rel=1e-6)
    assert stats["laplacian_var"] == pytest.approx(lap_var, rel=1e-5)
    assert stats["dark_channel"] == pytest.approx(fog, rel=1e-9)


def test_airlight_is_the_mean_of_the_brightest_thousandth():
    image = np.zeros((100, 100), np.uint8)
    image[:2, :4] = 200  # 8 bright pixels, the top 10 dark-channel values with two more
    image[2, :2] = 100
    stats = image_quality(image, patch=1)
    assert stats[2] == pytest.approx((8 * 200 + 2 * 100) / 10000 / ((8 * 200 + 2 * 100) / 10))


def test_rejects_bad_input():
    with pytest.raises(ValueError, match="uint8"):
        image_quality(IMAGE.astype(np.float32))
    with pytest.raises(ValueError, match="odd"):
        image_quality(IMAGE, patch=4)


def test_fog_statistics_monotone_in_beta():
    rig = CameraRig()
    config = SceneConfig(
        texture_count=2, texture_px=256, ground_texture_px=512, box_density_per_m2=0.08
    )
    scene = build_scene(np.array([[0.0, 0.0], [20.0, 0.0]]), config, seed=2)
    centre = rig.body_translation_cam()
    radiance, distance = render_radiance(scene, rig, centre, rig.body_rotation_cam())
    imaging = ImagingConfig(
        camera=CameraModel(target_signal_electrons=1e12, read_noise_electrons=0.0)
    )
    stats = []
    for beta in (0.0, 0.01, 0.03, 0.1, 0.3):
        weather = FrameWeather(beta=beta, signal_electrons=1e12)
        image = expose(radiance, distance, weather, np.random.default_rng(0), imaging)
        stats.append(dict(zip(QUALITY_NAMES, image_quality(image), strict=True)))
    dark = [s["dark_channel"] for s in stats]
    contrast = [s["contrast"] for s in stats]
    sharpness = [s["laplacian_var"] for s in stats]
    assert np.all(np.diff(dark) > 0), dark
    assert np.all(np.diff(contrast) < 0), contrast
    assert np.all(np.diff(sharpness) < 0), sharpness
    # thick fog: the image tends to the airlight, the estimate to 1
    assert dark[-1] > 0.85 and dark[0] < 0.6
    assert dataclasses.asdict(FrameWeather())["beta"] == 0.0
