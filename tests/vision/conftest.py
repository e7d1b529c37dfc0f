"""A short rendered stereo run shared by the vision tests (4 s at 10 Hz, sunny)."""

from __future__ import annotations

import cv2
import pytest

from msf_torch.sim import simulate_run
from msf_torch.sim.render import RunRenderer, SceneConfig, render_sim_config

SCENE = SceneConfig(texture_count=4, texture_px=256, ground_texture_px=1024)


@pytest.fixture(autouse=True)
def _one_thread(one_torch_thread):
    """One torch thread for every vision test (``tests/conftest.py``): LM on small systems
    is slowest when oversubscribed."""


@pytest.fixture(scope="package")
def rendered():
    """(run, renderer, frames): a 4 s drive and its 41 rendered stereo frames."""
    cv2.setNumThreads(1)
    run = simulate_run(render_sim_config(duration_s=4.0), seed=3)
    renderer = RunRenderer.for_run(run, SCENE, seed=3)
    return run, renderer, [renderer.frame(k) for k in range(len(renderer))]


@pytest.fixture(scope="package")
def odometry(rendered):
    """The stereo odometry over the rendered run (default settings)."""
    from msf_torch.vision import StereoVisualOdometry

    _, renderer, frames = rendered
    return StereoVisualOdometry(renderer.rig).run(frames)
