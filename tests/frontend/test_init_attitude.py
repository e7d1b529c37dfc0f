"""Initial roll and pitch (frontend.init) from a still accelerometer, against the rotation
scipy builds from the true angles: at rest the accelerometer reads ``f = R^T (0, 0, g)``, and
with no heading source the yaw starts at 0, so the initial attitude must be
``Rz(0) Ry(pitch) Rx(roll)`` itself."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.init import initial_state
from msf_torch.types import ImuSamples, Sequence

DTYPE = torch.float64
G = 9.80665
ROLL_PITCH = [(0.3, -0.2), (-1.1, 0.6), (2.5, 1.2)]  # rad; the last one upside down


def test_roll_and_pitch_from_a_still_accelerometer():
    truth = Rotation.from_euler("ZYX", [[0.0, pitch, roll] for roll, pitch in ROLL_PITCH])
    rot = truth.as_matrix()  # (B, 3, 3) body -> world
    batch, n = rot.shape[0], 101
    accel = np.einsum("bji,j->bi", rot, [0.0, 0.0, G])  # R^T (0, 0, g)
    seq = Sequence(
        names=[f"still{b}" for b in range(batch)],
        imu=ImuSamples(
            t=torch.linspace(0.0, 1.0, n, dtype=DTYPE).expand(batch, n).clone(),
            gyro=torch.zeros(batch, n, 3, dtype=DTYPE),
            accel=torch.as_tensor(accel)[:, None, :].expand(batch, n, 3).clone(),
            mask=torch.ones(batch, n, dtype=torch.bool),
        ),
    )
    seq.check()
    state, _ = initial_state(seq, EskfConfig(gravity_mps2=G))
    np.testing.assert_allclose(state.rotation.numpy(), rot, rtol=0, atol=1e-12)
