"""The estimators by name."""

from __future__ import annotations

from stages.ranging.centroid import centroid
from stages.ranging.fast import fast
from stages.ranging.gaussfit import gaussfit
from stages.ranging.histograms import Histograms
from stages.ranging.matched import matched
from stages.ranging.ml import ml

ESTIMATORS = ("fast", "centroid", "matched", "gaussfit", "ml")


ESTIMATOR_FUNCS = {"centroid": centroid, "matched": matched, "gaussfit": gaussfit, "ml": ml,
                   "fast": fast}


def estimate(h: Histograms, sigma_s: float, estimator: str = "ml", p_fa: float = 1e-3):
    """Run one estimator by name (see :data:`ESTIMATORS`)."""
    if estimator not in ESTIMATOR_FUNCS:
        raise ValueError(f"estimator must be one of {ESTIMATORS}, found {estimator!r}")
    return ESTIMATOR_FUNCS[estimator](h, sigma_s, p_fa)
