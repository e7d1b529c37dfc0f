"""The front end does not depend on where the world origin lies.

A simulated 30 s run (IMU + wheels + GNSS, heading from the GNSS track) is filtered as
recorded and with every GNSS fix moved by 1 km, 60 km and 5000 km (a UTM northing): the
estimated trajectory moves by the offset and the conventional covariance stays the same
(measured 7e-13 / 9e-11 / 1.4e-8 m, covariance 1e-13 / 7e-12 / 1.2e-9 relative). Corrections
that swung the position about the origin (``p = Exp(xi_R) p_hat + xi_p``) made the same kind
of run diverge 1 km away; a covariance about the world origin instead of the estimate lost
0.25 m to round-off 1000 km away.
"""

from __future__ import annotations

import copy

import pytest
import torch

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.eskf import run_eskf
from msf_torch.sim import SimConfig, simulate_run

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.mark.parametrize(
    ("offset_m", "position_tol_m", "covariance_tol"),
    [(1e3, 1e-10, 1e-10), (6e4, 1e-9, 1e-10), (5e6, 1e-6, 1e-7)],
)
def test_trajectory_moves_with_the_origin(
    offset_m: float, position_tol_m: float, covariance_tol: float
):
    run = simulate_run(SimConfig(duration_s=30.0, slip_episodes=0, gnss_outage_count=0), seed=7)
    cfg = EskfConfig(slip_detection=False)
    base = run_eskf(run.sequence, cfg)
    moved = copy.deepcopy(run.sequence)
    shift = torch.tensor([offset_m, -0.5 * offset_m, 0.0], dtype=torch.float64)
    moved.gnss.position[...] = moved.gnss.position + shift
    result = run_eskf(moved, cfg)
    assert torch.equal(result.mask, base.mask)
    error = float((result.position - shift - base.position).abs().max())
    assert error < position_tol_m, error
    scale = base.covariance.abs().amax((-2, -1), keepdim=True)
    change = float(((result.covariance - base.covariance) / scale).abs().max())
    assert change < covariance_tol, change
