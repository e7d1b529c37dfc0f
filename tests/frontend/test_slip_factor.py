"""Wheel slip factor (frontend.slip) against its closed form, row by row in plain Python:
``q = d_v^2 / s_v + d_w^2 / s_w``, ``f = min(exp(-q / (2 k^2)), min(1, f_prev + rate dt))``;
the lateral and vertical rows play no part."""

from __future__ import annotations

import math

import pytest
import torch

from msf_torch.frontend.slip import slip_factor

DTYPE = torch.float64


@pytest.mark.parametrize("sensitivity", [0.5, 3.0])
def test_slip_factor_equals_closed_form(sensitivity):
    residual = torch.tensor(
        [
            [0.02, 5.0, -7.0, 0.001],  # calm: limited by the recovery from a low factor
            [0.9, 0.0, 0.0, -0.05],  # a wheel spinning: the factor drops at once
            [-0.3, 0.1, 0.2, 0.2],
            [0.0, 9.0, 9.0, 0.0],  # lateral and vertical rows only: no slip
        ],
        dtype=DTYPE,
    )
    innovation_var = torch.tensor(
        [[0.01, 1.0, 1.0, 0.004], [0.04, 2.0, 2.0, 0.01], [0.09, 1.0, 1.0, 0.02], [0.01] * 4],
        dtype=DTYPE,
    )
    previous = torch.tensor([0.1, 1.0, 0.7, 0.95], dtype=DTYPE)
    elapsed = torch.tensor([0.04, 0.04, 0.5, 0.2], dtype=DTYPE)
    rate = 1.5
    got = slip_factor(residual, innovation_var, previous, elapsed, sensitivity, rate)
    for b in range(4):
        d, s = residual[b].tolist(), innovation_var[b].tolist()
        q = d[0] ** 2 / s[0] + d[3] ** 2 / s[3]
        raw = math.exp(-q / (2.0 * sensitivity**2))
        want = min(raw, min(1.0, float(previous[b]) + rate * float(elapsed[b])))
        assert float(got[b]) == pytest.approx(want, rel=1e-12, abs=1e-300), b
    # both branches of the minimum are taken (with k = 0.5 and k = 3 alike)
    assert float(got[0]) == pytest.approx(0.1 + rate * 0.04, rel=1e-12)
    assert float(got[3]) == 1.0
    assert float(got[1]) < float(previous[1])
