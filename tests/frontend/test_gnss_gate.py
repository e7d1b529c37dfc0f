"""The ESKF's chi-square gate on GNSS fixes: a fix is fused exactly when its NIS lies below
the 3-degree-of-freedom quantile at ``gate_probability``, taken here from a printed
chi-square table (11.345 at 0.99; the 4-dof quantile is 13.277). The fixes claim half their
true sigma, so their NIS spreads over both sides of the gate and between the two quantiles."""

from __future__ import annotations

import torch

from msf_torch.frontend.config import EskfConfig
from msf_torch.frontend.eskf import run_eskf
from msf_torch.sim import SimConfig, simulate_run

CHI2_3DOF_099 = 11.345  # chi-square table, 3 degrees of freedom, upper 1 %
CHI2_4DOF_099 = 13.277


def test_gnss_fix_is_fused_exactly_below_the_three_dof_quantile():
    seq = simulate_run(SimConfig(duration_s=40.0), seed=1).sequence
    seq.gnss.sigma.mul_(0.5)
    cfg = EskfConfig(gate_probability=0.99, gate_reopen_after=10**6)  # no re-opening
    with torch.no_grad():
        result = run_eskf(seq, cfg)
    present = result.present["gnss"]
    nis, accepted = result.nis["gnss"][present], result.accepted["gnss"][present]
    assert nis.numel() == 40
    between = (nis > CHI2_3DOF_099) & (nis < CHI2_4DOF_099)
    assert bool(between.any()) and bool(accepted.any()) and not bool(accepted.all())
    assert ((nis - CHI2_3DOF_099).abs() > 1e-2).all()  # no fix on the table's rounding
    torch.testing.assert_close(accepted, nis < CHI2_3DOF_099, rtol=0, atol=0)
