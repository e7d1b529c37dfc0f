"""Evaluation: association and Umeyama alignment, ATE / RPE (as evo defines them), NEES and
its chi-square test, overview plots.

``plots`` is not imported here (it pulls in matplotlib); use
``from msf_torch.eval.plots import overview_figure``.
"""

from msf_torch.eval import align, metrics, nees
from msf_torch.eval.align import associate, umeyama
from msf_torch.eval.metrics import ate, evaluate_files, position_errors, rpe
from msf_torch.eval.nees import chi2_interval, fraction_inside

__all__ = [
    "align",
    "metrics",
    "nees",
    "associate",
    "umeyama",
    "ate",
    "rpe",
    "position_errors",
    "evaluate_files",
    "chi2_interval",
    "fraction_inside",
]
