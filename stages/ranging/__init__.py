"""Range estimation from first-photon histograms: centroid (eq. 2.10), matched filter,
the thesis's Gaussian fit (the baseline), and a Poisson maximum likelihood with pile-up.

Histograms arrive in code order; with reversed timing the first photon is the highest code,
so everything here works in arrival order (codes reversed) on the time axis the calibration
gives (bin edges from the INL and LSB).

Pile-up without approximation: going through the bins in arrival order, a cycle whose TDC
has not started yet is "at risk"; bin j's hits are Binomial(R_j, 1 - exp(-lambda_j)) given
the R_j cycles at risk, where lambda_j is the undistorted intensity (signal Gaussian plus
flat background). The likelihood of a first-photon histogram factorises into these
binomials exactly, so the ML estimator fits the undistorted model and is unbiased at any
M; the same step (``lambda = -log(1 - h / R)``, Coates) corrects the histogram for the fast
estimators.
"""

from stages.ranging._numba import numba
from stages.ranging.centroid import centroid
from stages.ranging.detection import (
    TAIL_EXACT_MAX,
    _background,
    _detect,
    _detection,
    _peak_index,
    detection_threshold,
    poisson_tail,
    tested_bin,
)
from stages.ranging.fast import (
    SCORING_STEPS,
    _coarse_to_fine_numpy,
    _fast_args,
    _fast_numpy,
    _fast_params,
    _score_steps_numpy,
    fast,
)
from stages.ranging.gauss_table import _CDF_PDF_TAB, _cdf_pdf_numpy
from stages.ranging.gaussfit import gaussfit
from stages.ranging.histograms import Estimate, Histograms
from stages.ranging.matched import matched
from stages.ranging.ml import _ml_numpy, _ml_setup, ml
from stages.ranging.multi import MAX_RETURNS, estimate_returns
from stages.ranging.registry import ESTIMATOR_FUNCS, ESTIMATORS, estimate
from stages.ranging.width import response_from_data, return_fwhm

if numba is not None:
    from stages.ranging.detection import _poisson_tail
    from stages.ranging.fast import _fast_numba
    from stages.ranging.gauss_table import _cdf_pdf
    from stages.ranging.ml import _ml_numba

#: the names this package has always exported (the module's before it became a package);
#: the compiled kernels (``_poisson_tail``, ``_cdf_pdf``, ``_fast_numba``, ``_ml_numba``)
#: too where numba is installed
__all__ = ["ESTIMATORS", "ESTIMATOR_FUNCS", "SCORING_STEPS", "TAIL_EXACT_MAX", "Estimate",
           "Histograms", "centroid", "detection_threshold", "estimate", "fast", "gaussfit",
           "matched", "ml", "numba", "poisson_tail", "tested_bin", "MAX_RETURNS",
           "estimate_returns", "response_from_data", "return_fwhm",
           "_CDF_PDF_TAB", "_background", "_cdf_pdf_numpy", "_coarse_to_fine_numpy",
           "_detect", "_detection", "_fast_args", "_fast_numpy", "_fast_params",
           "_ml_numpy", "_ml_setup", "_peak_index", "_score_steps_numpy"]
if numba is not None:
    __all__ += ["_poisson_tail", "_cdf_pdf", "_fast_numba", "_ml_numba"]
