"""``invariant_retract`` against its closed form written with scipy's rotations, far from the
origin and with large rotation errors: ``R = Exp(xi_R) R_hat``, ``v = Exp(xi_R) v_hat + xi_v``,
``p = p_hat + xi_p - [p_hat]x xi_R`` (the position is shifted, never swung about the world
origin). The round trip with ``invariant_difference`` cannot see a change made to both
functions alike (swinging ``p_hat`` by ``Exp(xi_R)`` in both agrees to first order), this can."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from msf_torch.geometry.invariant import invariant_difference, invariant_retract

DT = torch.float64


def test_retract_and_difference_equal_the_closed_form():
    rng = np.random.default_rng(5)
    batch = 16
    position = rng.normal(size=(batch, 3)) * 2000.0  # km from the origin
    velocity = rng.normal(size=(batch, 3)) * 10.0
    rotation = Rotation.from_rotvec(rng.normal(size=(batch, 3))).as_matrix()
    xi = rng.normal(size=(batch, 9)) * np.repeat([1.0, 0.5, 0.4], 3)
    turn = Rotation.from_rotvec(xi[:, 6:9]).as_matrix()
    want_p = position + xi[:, 0:3] - np.cross(position, xi[:, 6:9])
    want_v = np.einsum("bij,bj->bi", turn, velocity) + xi[:, 3:6]
    want_r = turn @ rotation
    estimate = [torch.as_tensor(x, dtype=DT) for x in (position, velocity, rotation)]
    p, v, r = invariant_retract(*estimate, torch.as_tensor(xi, dtype=DT))
    np.testing.assert_allclose(p.numpy(), want_p, rtol=0, atol=1e-9)
    np.testing.assert_allclose(v.numpy(), want_v, rtol=0, atol=1e-12)
    np.testing.assert_allclose(r.numpy(), want_r, rtol=0, atol=1e-12)
    truth = [torch.as_tensor(x, dtype=DT) for x in (want_p, want_v, want_r)]
    back = invariant_difference(*truth, *estimate)
    np.testing.assert_allclose(back.numpy(), xi, rtol=0, atol=1e-9)
