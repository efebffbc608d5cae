"""The Gaussian's CDF and density from a table (the fast estimator's scoring steps), the
compiled form beside its numpy twin."""

from __future__ import annotations

import numpy as np
from scipy.special import ndtr

from stages.models.tcspc import SQRT2PI
from stages.ranging._numba import numba

# The Gaussian's CDF and density for the scoring steps: a table every 1/32 sigma over
# +-9 sigma of the third-order Taylor polynomials in d = z - z0 about each entry z0
# (|d| <= 1/64: error ~2e-9), eight coefficients to an entry (one cache line): two
# Horner evaluations an edge, a tenth of the cost of erfc and exp.
_Z_MAX, _Z_PER = 9.0, 32


def _coefficients() -> np.ndarray:
    z0 = np.arange(-_Z_MAX * _Z_PER, _Z_MAX * _Z_PER + 1) / _Z_PER
    c0, f, q = ndtr(z0), np.exp(-0.5 * z0 ** 2) / SQRT2PI, z0 * z0 - 1.0
    tab = np.stack([c0, f, -0.5 * f * z0, f * q / 6.0,                      # Phi
                    f, -f * z0, 0.5 * f * q, -f * (z0 * q - 2.0 * z0) / 6.0], 1)  # phi
    tab.flags.writeable = False
    return np.ascontiguousarray(tab)


_CDF_PDF_TAB = _coefficients()


def _cdf_pdf_numpy(z):
    """Phi(z) and phi(z) from the table (the compiled ``_cdf_pdf``'s twin)."""
    zc = np.minimum(np.maximum(z, -_Z_MAX), _Z_MAX)
    i = ((zc + _Z_MAX) * _Z_PER + 0.5).astype(np.int64)  # >= 0: truncation is floor
    d = zc - (i / _Z_PER - _Z_MAX)
    a = _CDF_PDF_TAB[i]
    a = np.moveaxis(a, -1, 0)
    return (a[0] + d * (a[1] + d * (a[2] + d * a[3])),
            a[4] + d * (a[5] + d * (a[6] + d * a[7])))
#: Fisher-scoring steps after the centroid, at most; a pixel stops once a step moves its


if numba is not None:
    @numba.njit(cache=True, nogil=True, inline="always")
    def _cdf_pdf(z):
        zc = min(max(z, -_Z_MAX), _Z_MAX)
        i = int((zc + _Z_MAX) * _Z_PER + 0.5)
        d = zc - (i / _Z_PER - _Z_MAX)
        a = _CDF_PDF_TAB
        return (a[i, 0] + d * (a[i, 1] + d * (a[i, 2] + d * a[i, 3])),
                a[i, 4] + d * (a[i, 5] + d * (a[i, 6] + d * a[i, 7])))

