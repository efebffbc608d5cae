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

The capture is another chip's where, pooled over its TDCs, the chi-square's excess is
``REFUSE_SIGMAS`` of its spread beyond what widths differing by ``SAME_CHIP_MAX_LSB`` RMS
would give: a model error or a DNL drifting with conditions smaller than that is no other
chip however many counts show it (a return firing in most cycles left ~0.03-0.06 LSB; the
zoo's chips differ by 0.11-0.17 LSB RMS a code). Where the counts could not see a
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
#: ... as this many sigmas beyond ``SAME_CHIP_MAX_LSB`` (the zoo's other chips showed 1.3-2.7x
#: what 0.1 LSB gives).
DECIDE_SIGMAS = 6.0
#: Another chip's: a pooled excess over this many sigmas ...
REFUSE_SIGMAS = 6.0
#: ... beyond this RMS width difference (LSB a code): what the same chip may show.
SAME_CHIP_MAX_LSB = 0.05
#: A TDC is named as disagreeing where its own excess beyond ``SAME_CHIP_MAX_LSB`` is over
#: this many sigmas.
TDC_SIGMAS = 3.0
#: A code this many sigmas above the calibration's pattern is a return (never a DNL): it
#: and ``RETURN_REACH`` codes each side are left out.
RETURN_Z, RETURN_REACH = 6.0, 4
#: ... and so are 3, 8 or 24 adjacent codes whose sum is this many of its sigmas above
#: it (a dim return; a bright one's tail, tens of codes where a return that fires in most
#: cycles is thousands of times the background a code): another chip's widths differ code
#: by code, with the 8-code pattern summing to ~0
CLUSTER_Z = 4.0


@dataclass(frozen=True)
class ChipCheck:
    """Per TDC, how a capture's code-density pattern agrees with a calibration's; pooled,
    the verdict."""

    chi2: np.ndarray      #: chi-square of the capture's widths against the calibration's
    dof: np.ndarray       #: its degrees of freedom (codes used - 1), 0 where none
    excess: np.ndarray    #: chi2 less the counting's share (per TDC)
    spread: np.ndarray    #: sqrt(2 dof): the chi-square's own sigma
    rate2: np.ndarray     #: sum of r^2 / var over the codes (the excess per LSB^2)
    tdc_ok: np.ndarray    #: TDCs with codes to compare

    def _beyond(self, diff_lsb: float) -> np.ndarray:
        """Per TDC, the excess beyond what widths ``diff_lsb`` apart would give."""
        return self.excess - diff_lsb ** 2 * self.rate2

    def _pooled_sigmas(self, values) -> float:
        sel = self.tdc_ok
        sd = float(np.sqrt(np.sum(self.spread[sel] ** 2)))
        return float(np.sum(np.asarray(values)[sel])) / sd if sd > 0 else 0.0

    @property
    def excess_sigmas(self) -> float:
        """The pooled chi-square's excess in its own sigmas."""
        return self._pooled_sigmas(self.excess)

    @property
    def beyond_sigmas(self) -> float:
        """The pooled excess beyond ``SAME_CHIP_MAX_LSB``, in sigmas."""
        return self._pooled_sigmas(self._beyond(SAME_CHIP_MAX_LSB))

    @property
    def power_sigmas(self) -> float:
        """What :attr:`beyond_sigmas` would be for widths ``DNL_DIFF_LSB`` apart."""
        return self._pooled_sigmas((DNL_DIFF_LSB ** 2 - SAME_CHIP_MAX_LSB ** 2) * self.rate2)

    @property
    def width_diff_lsb(self) -> float:
        """The RMS width difference (LSB a code) the pooled excess stands for (0 where
        the counting explains it all)."""
        sel = self.tdc_ok
        d2 = float(np.sum(self.excess[sel])) / max(float(np.sum(self.rate2[sel])), 1e-300)
        return float(np.sqrt(max(d2, 0.0)))

    @property
    def n_tdc(self) -> int:
        return int(self.chi2.size)

    @property
    def disagree(self) -> np.ndarray:
        """The TDCs that disagree on their own (``TDC_SIGMAS``)."""
        return self.disagree_at(TDC_SIGMAS)

    def disagree_at(self, sigmas: float) -> np.ndarray:
        """The TDCs whose own excess beyond ``SAME_CHIP_MAX_LSB`` is over ``sigmas``."""
        with np.errstate(divide="ignore", invalid="ignore"):
            z = self._beyond(SAME_CHIP_MAX_LSB) / self.spread
        return self.tdc_ok & (z > sigmas)

    @property
    def verdict(self) -> str:
        """"mismatch" (another chip's calibration), "match", or "undecided" (too few
        background counts to see another chip: a dim capture)."""
        if self.beyond_sigmas > REFUSE_SIGMAS:
            return "mismatch"
        return "match" if self.power_sigmas >= DECIDE_SIGMAS else "undecided"

    def summary(self) -> str:
        return (f"code widths {self.width_diff_lsb:.3f} LSB RMS from the calibration's over "
                f"{int(self.tdc_ok.sum())} TDCs ({self.beyond_sigmas:.1f} sigma beyond "
                f"{SAME_CHIP_MAX_LSB} LSB; {DNL_DIFF_LSB} LSB would show at "
                f"{self.power_sigmas:.1f})")


def check_chip(hits: np.ndarray, cycles, widths: np.ndarray, width_var=None,
               exclude: np.ndarray | None = None, rounds: int = 6) -> ChipCheck:
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
        hot = z > RETURN_Z
        for span in (3, 8, 24):  # a dim return's codes, a bright one's tail
            run = np.cumsum(np.concatenate([np.zeros((z.shape[0], 1)), z], axis=1), axis=1)
            lo = np.clip(np.arange(N_CODES) - span // 2, 0, N_CODES)
            hi = np.clip(lo + span, 0, N_CODES)
            hot |= (run[:, hi] - run[:, lo]) / np.sqrt(span) > CLUSTER_Z
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
    return ChipCheck(chi2, dof, chi2 - dof, np.sqrt(2 * dof), rate2, dof > 0)
