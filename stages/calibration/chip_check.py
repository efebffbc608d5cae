"""Calibration, whether a capture comes from the chip a calibration was made on (issue 33.4).

A capture carries its chip's code-density pattern in its own light: the uniform part of
every TDC's histogram (the background of a range capture) fills each code in proportion to
its width once pile-up is undone (Coates: ``r w_k = -log(1 - h_k / R_k)``, R_k the cycles
still at risk, the density test's own estimate). On the calibration's chip those are the
calibration's widths times one rate; on another chip they are that chip's widths, whose
random DNL (0.05-0.1 LSB a code on real chips) and pattern amplitude differ. Per TDC the
capture's ``r w_k`` are compared with ``r`` times the calibration's widths over the codes
clear of the window's edges and of any return, each code's variance the capture's counting
(binomial, at the calibrated width) and the calibration's own (its width variance): a
chi-square, and the RMS width difference its excess over the counting stands for. (A
chip's second-stage bounds n_min, n_max from a range capture were found unreliable; the
widths are measured from every background count.)

The capture is another chip's where, pooled over its TDCs, the chi-square's excess is over
``REFUSE_SIGMAS`` of its spread and the RMS width difference over ``SAME_CHIP_MAX_LSB`` (a
tiny model error over many counts, a DNL drifting with conditions, is no other chip: the
zoo's chips differ by 0.1-0.2 LSB RMS a code). Where the counts could not see a
difference of ``DNL_DIFF_LSB`` at ``DECIDE_SIGMAS`` the check is undecided (a dim
capture: too few background counts a code), and passes with a warning.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas.constants import N_CODES
from stages.calibration.reset_peak import EDGE_MARGIN, RESET_HALF, at_risk_by_code
from stages.calibration.timescale import light_end

#: The RMS width difference (LSB a code) a capture must be able to see to decide: two real
#: chips' random DNL (0.05-0.1 LSB each) differ by at least about this.
DNL_DIFF_LSB = 0.1
#: ... as this many sigmas of the pooled chi-square's excess.
DECIDE_SIGMAS = 10.0
#: Another chip's: a pooled excess over this many sigmas ...
REFUSE_SIGMAS = 6.0
#: ... and an RMS width difference over this (LSB a code).
SAME_CHIP_MAX_LSB = 0.04
#: A TDC is named as disagreeing where its own excess is over this many sigmas and its own
#: RMS width difference over ``SAME_CHIP_MAX_LSB``.
TDC_SIGMAS = 3.0
#: A code this many sigmas above the calibration's pattern is a return (never a DNL): it
#: and ``RETURN_REACH`` codes each side are left out.
RETURN_Z, RETURN_REACH = 6.0, 4
#: ... and so are three adjacent codes whose mean is this many sigmas above it (a dim
#: return; a DNL differs code by code, alternating with the 8-code pattern)
CLUSTER_Z = 4.0


@dataclass(frozen=True)
class ChipCheck:
    """Per TDC, how a capture's code-density pattern agrees with a calibration's; pooled,
    the verdict."""

    chi2: np.ndarray      #: chi-square of the capture's widths against the calibration's
    dof: np.ndarray       #: its degrees of freedom (codes used - 1), 0 where none
    excess: np.ndarray    #: chi2 less the counting's share (per TDC)
    spread: np.ndarray    #: sqrt(2 dof): the chi-square's own sigma
    power: np.ndarray     #: the excess widths ``DNL_DIFF_LSB`` apart would give
    rate2: np.ndarray     #: sum of r^2 / var over the codes (the excess per LSB^2)
    tdc_ok: np.ndarray    #: TDCs with codes to compare

    def _pooled(self, rows=None):
        sel = self.tdc_ok if rows is None else rows
        sd = float(np.sqrt(np.sum(self.spread[sel] ** 2)))
        return (float(np.sum(self.excess[sel])) / sd if sd > 0 else 0.0,
                float(np.sum(self.power[sel])) / sd if sd > 0 else 0.0,
                float(np.sum(self.excess[sel]) / max(np.sum(self.rate2[sel]), 1e-300)))

    @property
    def excess_sigmas(self) -> float:
        """The pooled chi-square's excess in its own sigmas."""
        return self._pooled()[0]

    @property
    def power_sigmas(self) -> float:
        """The pooled excess a difference of ``DNL_DIFF_LSB`` would give, in sigmas."""
        return self._pooled()[1]

    @property
    def width_diff_lsb(self) -> float:
        """The RMS width difference (LSB a code) the pooled excess stands for (0 where
        the counting explains it all)."""
        return float(np.sqrt(max(self._pooled()[2], 0.0)))

    @property
    def tdc_width_diff_lsb(self) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.sqrt(np.clip(self.excess / self.rate2, 0.0, None))

    @property
    def n_tdc(self) -> int:
        return int(self.chi2.size)

    @property
    def disagree(self) -> np.ndarray:
        """The TDCs that disagree on their own (``TDC_SIGMAS``, ``SAME_CHIP_MAX_LSB``)."""
        return self.disagree_at(TDC_SIGMAS)

    def disagree_at(self, sigmas: float) -> np.ndarray:
        """The TDCs whose own excess is over ``sigmas`` and whose widths differ by more
        than ``SAME_CHIP_MAX_LSB``."""
        with np.errstate(divide="ignore", invalid="ignore"):
            z = self.excess / self.spread
        return self.tdc_ok & (z > sigmas) & (self.tdc_width_diff_lsb > SAME_CHIP_MAX_LSB)

    @property
    def verdict(self) -> str:
        """"mismatch" (another chip's calibration), "match", or "undecided" (too few
        background counts to see another chip: a dim capture)."""
        z, power, _ = self._pooled()
        if z > REFUSE_SIGMAS and self.width_diff_lsb > SAME_CHIP_MAX_LSB:
            return "mismatch"
        return "match" if power >= DECIDE_SIGMAS else "undecided"

    def summary(self) -> str:
        return (f"code-density pattern: {self.excess_sigmas:.1f} sigma excess over "
                f"{int(self.tdc_ok.sum())} TDCs, RMS width difference "
                f"{self.width_diff_lsb:.3f} LSB (could see {DNL_DIFF_LSB} at "
                f"{self.power_sigmas:.1f} sigma)")


def check_chip(hits: np.ndarray, cycles, widths: np.ndarray, width_var=None,
               exclude: np.ndarray | None = None, rounds: int = 3) -> ChipCheck:
    """:class:`ChipCheck` of a capture's histograms ``hits`` (n_tdc, 512) over ``cycles``
    against a calibration's code ``widths`` (n_tdc, 512, LSB; NaN where not measured) and
    their variances ``width_var`` (LSB^2; None: taken as exact). ``exclude``: codes to
    leave out (e.g. around the returns a range found); codes far above the pattern
    (``RETURN_Z``) are left out too."""
    h = np.asarray(hits, np.float64)
    w = np.asarray(widths, np.float64)
    v = np.zeros_like(w) if width_var is None else np.nan_to_num(
        np.asarray(width_var, np.float64), nan=0.0)
    risk = at_risk_by_code(h, np.asarray(cycles, np.float64).reshape(-1))
    with np.errstate(divide="ignore", invalid="ignore"):
        rw = -np.log1p(-np.clip(h / risk, 0.0, 1.0 - 1e-12))
    top, _ = light_end(h)
    k = np.arange(N_CODES)[None, :]
    use = ((k >= 2) & (k < (top - RESET_HALF - EDGE_MARGIN - 2)[:, None])
           & np.isfinite(w) & (w > 0.05) & (risk > h) & (risk > 0))
    if exclude is not None:
        use &= ~np.asarray(exclude, bool)

    def residuals(use):  # the rate, each code's variance and its z
        r = np.where(use, rw, 0.0).sum(1) / np.maximum(np.where(use, w, 0.0).sum(1), 1e-300)
        p = -np.expm1(-r[:, None] * np.where(use, w, 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            var = p / (risk * np.maximum(1 - p, 1e-12)) + r[:, None] ** 2 * v
            z = np.where(use & (var > 0), (rw - r[:, None] * w) / np.sqrt(var), 0.0)
        return r, var, z

    for _ in range(rounds):  # the returns left out, and the rate again without them
        r, var, z = residuals(use)
        near = (z + np.roll(z, 1, axis=1) + np.roll(z, -1, axis=1)) / np.sqrt(3)
        hot = (z > RETURN_Z) | (near > CLUSTER_Z)
        if not hot.any():
            break
        spread = np.zeros_like(hot)
        for d in range(-RETURN_REACH, RETURN_REACH + 1):
            spread |= np.roll(hot, d, axis=1)
        use &= ~spread
    r, var, z = residuals(use)
    good = use & (var > 0)
    m = good.sum(1)
    chi2 = np.where(good, z * z, 0.0).sum(1)
    dof = np.maximum(m - 1, 0).astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        rate2 = np.where(good, r[:, None] ** 2 / var, 0.0).sum(1)
    return ChipCheck(chi2, dof, chi2 - dof, np.sqrt(2 * dof), rate2 * DNL_DIFF_LSB ** 2,
                     rate2, dof > 0)
