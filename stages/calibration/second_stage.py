"""Calibration, the second stage (eq. 3.4): Nmin/Nmax/Nth/PDM of every TDC from the joint
counts of (TDC, P1st, D2nd) over hit candidates, one capture or a whole campaign.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas.constants import N_CODES_2ND
from schemas.errors import CalibrationError
from stages.artifact import ArtifactBounds, estimate_bounds


class SecondStageAccumulator:
    """Joint counts of (TDC, P1st, D2nd) over hit candidates, for Nmin/Nmax/Nth/PDM."""

    def __init__(self, n_tdc: int):
        self.n_tdc = n_tdc
        self.counts = np.zeros((n_tdc, 8, N_CODES_2ND), np.int64)

    def update(self, words: np.ndarray, first_word: int = 0) -> None:
        from stages.codec import classify_words, decode_fields

        f = decode_fields(words)
        cls = classify_words(words, self.n_tdc, first_word, fields=f)
        ok = cls == 0  # hit candidates: no artifact test yet (bounds unknown)
        pos = (np.arange(words.size) + first_word) % self.n_tdc
        key = (pos[ok] * 8 + f.p1st[ok]) * N_CODES_2ND + f.d2nd[ok]
        self.counts += np.bincount(key, minlength=self.counts.size).reshape(self.counts.shape)


@dataclass(frozen=True)
class SecondStage:
    n_min: np.ndarray
    n_max: np.ndarray
    n_th: np.ndarray
    pdm: np.ndarray
    #: per TDC, why its bounds cannot be trusted ("" where they can; () where none is
    #: recorded): :attr:`stages.artifact.ArtifactBounds.reasons` of the estimate
    reasons: tuple = ()

    @property
    def uncertain(self) -> np.ndarray:
        n = np.asarray(self.n_min).size
        return np.array([bool(r) for r in self.reasons], bool) if self.reasons else \
            np.zeros(n, bool)

    @property
    def bounds(self) -> ArtifactBounds:
        return ArtifactBounds(self.n_min, self.n_max, source="density test",
                              uncertain=self.uncertain, reasons=self.reasons)


def second_stage_params(joint: np.ndarray, bounds: ArtifactBounds | None = None
                        ) -> SecondStage:
    """Nmin, Nmax (the valid block, artifact excluded), Nth (min D2nd with P1st = 0) and
    PDM (min D2nd with P1st = 4), per TDC (section 3.2). -1 where a TDC saw nothing.
    ``bounds``: Nmin/Nmax found elsewhere (:func:`campaign_second_stage`); by default
    estimated from ``joint``. The estimate's ``uncertain`` reasons are kept."""
    b = estimate_bounds(joint.sum(axis=1)) if bounds is None else bounds
    d2 = np.arange(N_CODES_2ND)
    inside = (d2 >= b.n_min[:, None]) & (d2 <= b.n_max[:, None])

    def first(p1):
        seen = (joint[:, p1, :] > 0) & inside
        return np.where(seen.any(axis=1), np.argmax(seen, axis=1), -1)

    empty = joint.sum(axis=(1, 2)) == 0
    n_min = np.where(empty, -1, b.n_min)
    n_max = np.where(empty, -1, b.n_max)
    return SecondStage(n_min, n_max, first(0), first(4), tuple(b.reasons))


def campaign_second_stage(joints: list, cycles: list) -> SecondStage:
    """One set of second-stage parameters for a whole campaign of density tests.

    The bounds are the chip's, not the light's (section 3.4): the artifact comes at a
    fixed rate per cycle whatever the light (it stays when V_op is 0 V), while the valid
    block grows with the light. So the test whose block holds the most counts per code
    per cycle has the clearest block-to-artifact contrast; each TDC takes its bounds from
    that test among those whose estimate is not ``uncertain`` (from the densest with its
    reason where every one is), and every test is filtered with them. A dim test alone
    can be fooled: with the artifact at 2.7e-3 a cycle the artifact's D2nd codes at 0.02
    detections a cycle were as dense as the block's, the block ran to 255 unflagged
    (issue 15). Nth and PDM (the smallest D2nd at P1st 0 and
    4 inside the bounds) come from all the tests summed: the most cycles seen.

    ``joints``: each test's ``SecondStageAccumulator.counts`` (n_tdc, 8, 256);
    ``cycles``: each test's cycles.
    """
    joints = [np.asarray(j) for j in joints]
    if not joints:
        raise CalibrationError("campaign_second_stage: no density test")
    per = [estimate_bounds(j.sum(axis=1)) for j in joints]
    n_tdc = joints[0].shape[0]
    density = np.zeros((len(joints), n_tdc))
    for i, (j, b, c) in enumerate(zip(joints, per, cycles, strict=True)):
        d2 = j.sum(axis=1).astype(np.float64)
        width = (b.n_max.astype(np.int64) - b.n_min + 1).clip(1)
        density[i] = (d2 * b.in_block()).sum(axis=1) / width / max(float(c), 1.0)
    # an estimate the data cannot vouch for loses to any it can (a very bright test's
    # block can be cut where pile-up and its reset peak skew the D2nd codes: uncertain,
    # and then its narrow block looks the densest)
    certain = np.stack([~b.uncertain for b in per])
    pick = np.argmax(np.where(certain, density, density - np.inf), axis=0)
    pick = np.where(certain.any(axis=0), pick, np.argmax(density, axis=0))
    rows = np.arange(n_tdc)

    def chosen(field):
        return np.stack([getattr(b, field) for b in per])[pick, rows]

    reasons = np.array([b.reasons for b in per], dtype=object)[pick, rows]
    bounds = ArtifactBounds(chosen("n_min"), chosen("n_max"), source="density tests",
                            uncertain=chosen("uncertain"), reasons=tuple(reasons.tolist()))
    return second_stage_params(sum(joints[1:], joints[0].copy()), bounds)
