"""Every sensor residual's error-state Jacobian against central finite differences and autograd.

Perturbation convention (``geometry.conventions``): ``p + dp``, ``v + dv``, ``R Exp(dtheta)``,
``b_g + db_g``, ``b_a + db_a``; Jacobians are ``dr / d(dx)`` at ``dx = 0``.
"""

from __future__ import annotations

from dataclasses import dataclass

import pytest
import torch

from msf_torch.geometry import so3
from msf_torch.sensors import (
    body_velocity_residual,
    gnss_heading_residual,
    gnss_residual,
    gnss_velocity_residual,
    nonholonomic_residual,
    pose_residual,
    wheel_residual,
    wheel_speed_and_yaw_rate,
    zero_velocity_residual,
)
from msf_torch.sensors.magnetometer import magnetometer_heading_residual

DTYPE = torch.float64


@dataclass
class State:
    position: torch.Tensor
    velocity: torch.Tensor
    rotation: torch.Tensor
    gyro_bias: torch.Tensor
    accel_bias: torch.Tensor

    def boxplus(self, dx: torch.Tensor) -> State:
        return State(
            self.position + dx[..., 0:3],
            self.velocity + dx[..., 3:6],
            self.rotation @ so3.exp(dx[..., 6:9]),
            self.gyro_bias + dx[..., 9:12],
            self.accel_bias + dx[..., 12:15],
        )


def _random_state(batch: int, gen: torch.Generator) -> State:
    def randn(*shape, scale=1.0):
        return scale * torch.randn(batch, *shape, generator=gen, dtype=DTYPE)

    return State(
        position=randn(3, scale=20.0),
        velocity=randn(3, scale=2.0),
        rotation=so3.exp(randn(3, scale=1.5)),
        gyro_bias=randn(3, scale=0.01),
        accel_bias=randn(3, scale=0.05),
    )


def _inputs(batch: int, seed: int):
    gen = torch.Generator().manual_seed(seed)
    state = _random_state(batch, gen)
    extra = {
        "gyro": 0.5 * torch.randn(batch, 3, generator=gen, dtype=DTYPE),
        "lever": torch.tensor([0.3, -0.2, 0.5], dtype=DTYPE)
        + 0.1 * torch.randn(batch, 3, generator=gen, dtype=DTYPE),
        "measured3": torch.randn(batch, 3, generator=gen, dtype=DTYPE),
        "left": 1.0 + 0.3 * torch.randn(batch, generator=gen, dtype=DTYPE),
        "right": 1.0 + 0.3 * torch.randn(batch, generator=gen, dtype=DTYPE),
        "measured_rotation": so3.exp(1.5 * torch.randn(batch, 3, generator=gen, dtype=DTYPE)),
    }
    # measurement near the state so the pose residual stays well inside the Log's domain
    extra["measured_position"] = state.position + torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    extra["pose_rotation"] = state.rotation @ so3.exp(
        0.5 * torch.randn(batch, 3, generator=gen, dtype=DTYPE)
    )
    # a heading within ~0.3 rad of the baseline's azimuth: the residual stays off its wrap
    baseline_world = (state.rotation @ extra["lever"][..., None])[..., 0]
    extra["heading"] = torch.atan2(baseline_world[:, 0], baseline_world[:, 1]) + 0.3 * torch.randn(
        batch, generator=gen, dtype=DTYPE
    )
    # an earth field (uT) with a strong vertical part, and a declination within ~0.3 rad of
    # the azimuth it has in the world
    extra["field"] = torch.tensor([18.0, 2.0, -40.0], dtype=DTYPE) + 3.0 * torch.randn(
        batch, 3, generator=gen, dtype=DTYPE
    )
    field_world = (state.rotation @ extra["field"][..., None])[..., 0]
    extra["declination"] = torch.atan2(field_world[:, 0], field_world[:, 1]) + 0.3 * torch.randn(
        batch, generator=gen, dtype=DTYPE
    )
    return state, extra


TRACK = 0.55


def _residuals(x: dict):
    """name -> fn(state) -> (residual, jacobian), measurements fixed."""
    return {
        "wheel": lambda s: wheel_residual(
            s.velocity, s.rotation, x["gyro"], s.gyro_bias, x["left"], x["right"], TRACK, x["lever"]
        ),
        "body_velocity": lambda s: body_velocity_residual(
            s.velocity, s.rotation, x["gyro"], s.gyro_bias, x["lever"], x["measured3"]
        ),
        "nonholonomic": lambda s: nonholonomic_residual(
            s.velocity, s.rotation, x["gyro"], s.gyro_bias, x["lever"]
        ),
        "zero_velocity": lambda s: zero_velocity_residual(s.velocity),
        "gnss": lambda s: gnss_residual(s.position, s.rotation, x["lever"], x["measured3"]),
        "gnss_velocity": lambda s: gnss_velocity_residual(
            s.velocity, s.rotation, x["gyro"], s.gyro_bias, x["lever"], x["measured3"]
        ),
        "gnss_heading": lambda s: gnss_heading_residual(s.rotation, x["lever"], x["heading"]),
        "magnetometer": lambda s: magnetometer_heading_residual(
            s.rotation, x["field"], x["declination"]
        ),
        "pose": lambda s: pose_residual(
            s.position, s.rotation, x["measured_position"], x["pose_rotation"]
        ),
    }


NAMES = [
    "wheel",
    "body_velocity",
    "nonholonomic",
    "zero_velocity",
    "gnss",
    "gnss_velocity",
    "gnss_heading",
    "magnetometer",
    "pose",
]
DIMS = {
    "wheel": 4,
    "body_velocity": 3,
    "nonholonomic": 2,
    "zero_velocity": 3,
    "gnss": 3,
    "gnss_velocity": 3,
    "gnss_heading": 1,
    "magnetometer": 1,
    "pose": 6,
}


def _finite_difference(fn, state: State, batch: int, h: float = 1e-6) -> torch.Tensor:
    cols = []
    for i in range(15):
        dx = torch.zeros(batch, 15, dtype=DTYPE)
        dx[:, i] = h
        plus = fn(state.boxplus(dx))[0]
        minus = fn(state.boxplus(-dx))[0]
        cols.append((plus - minus) / (2 * h))
    return torch.stack(cols, -1)


@pytest.mark.parametrize("batch", [1, 10])
@pytest.mark.parametrize("name", NAMES)
def test_jacobian_matches_central_differences(name, batch):
    state, extra = _inputs(batch, seed=30 + NAMES.index(name))
    fn = _residuals(extra)[name]
    residual, jac = fn(state)
    assert residual.shape == (batch, DIMS[name])
    assert jac.shape == (batch, DIMS[name], 15)
    numeric = _finite_difference(fn, state, batch)
    torch.testing.assert_close(jac, numeric, rtol=0, atol=1e-6)


@pytest.mark.parametrize("name", NAMES)
def test_jacobian_matches_autograd(name):
    """Second route: autograd of dx -> r(x [+] dx) at dx = 0, to rounding."""
    batch = 10
    state, extra = _inputs(batch, seed=40 + NAMES.index(name))
    fn = _residuals(extra)[name]
    _, jac = fn(state)

    def flat(dx: torch.Tensor) -> torch.Tensor:
        return fn(state.boxplus(dx.reshape(batch, 15)))[0]

    auto = torch.autograd.functional.jacobian(flat, torch.zeros(batch * 15, dtype=DTYPE))
    auto = auto.reshape(batch, DIMS[name], batch, 15)
    diag = torch.stack([auto[b, :, b, :] for b in range(batch)])
    torch.testing.assert_close(jac, diag, rtol=0, atol=1e-12)


def test_residual_values_and_signs():
    """r = h(x) - z: zero at a consistent measurement, signs as documented."""
    state, extra = _inputs(10, seed=50)
    lever = extra["lever"]
    antenna = state.position + (state.rotation @ lever[..., None])[..., 0]
    r, _ = gnss_residual(state.position, state.rotation, lever, antenna)
    torch.testing.assert_close(r, torch.zeros_like(r), rtol=0, atol=1e-13)
    r, _ = gnss_residual(state.position, state.rotation, lever, antenna - 1.0)
    torch.testing.assert_close(r, torch.ones_like(r), rtol=0, atol=1e-13)
    # the antenna's velocity: d/dt (p + R l) = v + R (w x l), w the bias-corrected rate;
    # the same by differencing the antenna position over a short rotation step
    rate = extra["gyro"] - state.gyro_bias
    step = 1e-6
    later = state.rotation @ so3.exp(step * rate)
    antenna_later = state.position + step * state.velocity + (later @ lever[..., None])[..., 0]
    doppler = (antenna_later - antenna) / step
    r, _ = gnss_velocity_residual(
        state.velocity, state.rotation, extra["gyro"], state.gyro_bias, lever, doppler
    )
    torch.testing.assert_close(r, torch.zeros_like(r), rtol=0, atol=1e-5)

    # wheel: build rim speeds from the true body velocity of the axle point
    omega = extra["gyro"] - state.gyro_bias
    omega[:, :2] = 0.0
    gyro = omega + state.gyro_bias
    lever = torch.tensor([-0.2, 0.0, 0.0], dtype=DTYPE).expand(10, 3)
    speed = 1.0 + torch.rand(10, generator=torch.Generator().manual_seed(51), dtype=DTYPE)
    body = torch.stack((speed, torch.zeros_like(speed), torch.zeros_like(speed)), -1)
    v_imu_body = body - torch.linalg.cross(omega, lever)
    velocity = (state.rotation @ v_imu_body[..., None])[..., 0]
    left = speed - omega[:, 2] * TRACK / 2
    right = speed + omega[:, 2] * TRACK / 2
    fwd, yaw_rate = wheel_speed_and_yaw_rate(left, right, TRACK)
    torch.testing.assert_close(fwd, speed, rtol=0, atol=1e-15)
    torch.testing.assert_close(yaw_rate, omega[:, 2], rtol=0, atol=1e-14)
    r, _ = wheel_residual(
        velocity, state.rotation, gyro, state.gyro_bias, left, right, TRACK, lever
    )
    torch.testing.assert_close(r, torch.zeros_like(r), rtol=0, atol=1e-13)
    r, _ = nonholonomic_residual(velocity, state.rotation, gyro, state.gyro_bias, lever)
    torch.testing.assert_close(r, torch.zeros_like(r), rtol=0, atol=1e-13)
    r, _ = wheel_residual(
        velocity, state.rotation, gyro, state.gyro_bias, left - 0.1, right - 0.1, TRACK, lever
    )
    torch.testing.assert_close(r[:, 0], torch.full((10,), 0.1, dtype=DTYPE), rtol=0, atol=1e-13)

    r, _ = pose_residual(
        state.position,
        state.rotation,
        state.position - 2.0,
        state.rotation @ so3.exp(torch.tensor([0.0, 0.0, -0.1], dtype=DTYPE)),
    )
    torch.testing.assert_close(r[:, :3], torch.full((10, 3), 2.0, dtype=DTYPE))
    torch.testing.assert_close(
        r[:, 3:], torch.tensor([0.0, 0.0, 0.1], dtype=DTYPE).expand(10, 3), rtol=0, atol=1e-13
    )
    r, _ = zero_velocity_residual(state.velocity)
    torch.testing.assert_close(r, state.velocity, rtol=0, atol=0)


def test_jacobians_broadcast_shared_lever_arm():
    """A (3,) lever arm shared by the batch gives the same Jacobians as a per-sample copy."""
    state, extra = _inputs(10, seed=52)
    lever = torch.tensor([0.4, 0.1, -0.3], dtype=DTYPE)
    for fn in (
        lambda lv: gnss_residual(state.position, state.rotation, lv, extra["measured3"]),
        lambda lv: wheel_residual(
            state.velocity,
            state.rotation,
            extra["gyro"],
            state.gyro_bias,
            extra["left"],
            extra["right"],
            TRACK,
            lv,
        ),
        lambda lv: nonholonomic_residual(
            state.velocity, state.rotation, extra["gyro"], state.gyro_bias, lv
        ),
    ):
        r1, j1 = fn(lever)
        r2, j2 = fn(lever.expand(10, 3))
        torch.testing.assert_close(r1, r2, rtol=0, atol=0)
        torch.testing.assert_close(j1, j2, rtol=0, atol=0)


def test_gnss_heading_closed_form_and_wrap():
    """A body yawed by ``a`` (ENU, counter-clockwise from east) with its secondary antenna
    straight ahead reads the azimuth ``pi/2 - a`` clockwise from north; a baseline to the
    left reads 90 degrees less; residuals wrap across north; a vertical baseline is inert."""
    yaw = torch.tensor([0.0, 0.4, 2.0, -2.9], dtype=DTYPE)
    rotation = so3.exp(torch.stack((0 * yaw, 0 * yaw, yaw), -1))
    ahead = torch.tensor([1.5, 0.0, 0.0], dtype=DTYPE)
    left = torch.tensor([0.0, 0.8, 0.0], dtype=DTYPE)
    azimuth = torch.pi / 2 - yaw
    r, jac = gnss_heading_residual(rotation, ahead, azimuth)
    torch.testing.assert_close(r[:, 0], torch.zeros_like(yaw), rtol=0, atol=1e-12)
    # a yaw error of +d (right perturbation about body z = world up when level) turns the
    # azimuth by -d: the Jacobian's yaw column is -1, roll / pitch do not move it
    torch.testing.assert_close(jac[:, 0, 6:9], torch.tensor([[0.0, 0.0, -1.0]] * 4, dtype=DTYPE))
    r, _ = gnss_heading_residual(rotation, left, azimuth - torch.pi / 2)
    torch.testing.assert_close(r[:, 0], torch.zeros_like(yaw), rtol=0, atol=1e-12)
    # heading 359 deg measured, 1 deg predicted: +2 deg, not -358
    north = so3.exp(torch.tensor([[0.0, 0.0, torch.pi / 2 - 0.5 * torch.pi / 90]], dtype=DTYPE))
    r, _ = gnss_heading_residual(
        north, ahead, torch.tensor([2 * torch.pi - torch.pi / 180], dtype=DTYPE)
    )
    torch.testing.assert_close(r[0, 0], torch.tensor(torch.pi / 90, dtype=DTYPE))
    r, jac = gnss_heading_residual(
        rotation[:1], torch.tensor([0.0, 0.0, 1.0], dtype=DTYPE), azimuth
    )
    assert float(r.abs().max()) == 0.0 and float(jac.abs().max()) == 0.0
