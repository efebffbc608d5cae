"""Contracts of the products: histograms, calibration tables and ranges (docs/design.md
"Outputs")."""

from __future__ import annotations

import pyarrow as pa

from schemas.core import SchemaSpec, field

HISTOGRAMS = SchemaSpec("histograms", "2.0", (
    field("measurement", pa.string(), "", "name of the measurement (capture or run)"),
    field("tdc", pa.uint16(), "", "TDC address (0-based); for an instrument's file the row it "
          "histograms: a PTU input channel, a LinoSPAD2 TDC or pixel (a generic file, "
          "written by any tool, may use any integer type for values 0..2^32 - 1)"),
    field("cycles", pa.uint64(), "cycle", "DAQ cycles this TDC was read in (every word at "
          "its position counts, whatever its class); a PTU T3 file: sync periods covered; "
          "LinoSPAD2: acquisition cycles"),
    field("counts", pa.list_(pa.uint64()), "count",
          "hits per code: D1st = 0..511 for the thesis chip (512 entries), dtime codes for "
          "a PTU T3 file, fine codes 0..139 for LinoSPAD2"),
    field("n_hit", pa.uint64(), "word", "hit words (sum of counts)"),
    field("n_no_hit", pa.uint64(), "word", "no_hit words (no START in the cycle)"),
    field("n_artifact", pa.uint64(), "word", "artifact words (D2nd outside [Nmin, Nmax])"),
    field("n_invalid_phase", pa.uint64(), "word", "words with a bubble in a phase code"),
    field("n_malformed", pa.uint64(), "word", "words with bad markers or address"),
    # 2.0: instruments other than the thesis chip (code count and bin width differ)
    field("instrument", pa.string(), "", "what made the counts: 'tcspc-chip' (Table 5.1 "
          "words; codes need the calibration's INL), 'picoquant-t3' (PTU T3 dtime codes), "
          "'linospad2' (fine codes of a carry chain), 'generic' (any instrument's "
          "histograms, written by any tool with only measurement, tdc, counts, instrument, "
          "bin_width_ps and optionally cycles and reference: [instruments_generic.md]"
          "(instruments_generic.md), with a Polars example)"),
    field("bin_width_ps", pa.float64(), "ps", "width of one code where the instrument "
          "states it (PTU resolution, LinoSPAD2 nominal 17.857 ps); null for the chip, "
          "whose code widths come from its calibration", nullable=True),
))

#: The major versions of ``histograms`` this software reads: 1.x (counts a fixed list of
#: 512, no instrument) is upgraded on read by :func:`pipeline.io.histograms.read_histograms`.
HISTOGRAMS_READS = (1, 2)

CALIBRATION_TDC = SchemaSpec("calibration_tdc", "1.1", (
    field("tdc", pa.uint16(), "", "TDC address (0-based)"),
    field("lsb_ps", pa.float64(), "ps", "LSB at the density test's intensity"),
    field("lsb_poly", pa.list_(pa.float64(), 4), "ps",
          "LSB as a cubic in detections per pixel per cycle (eq. 5.1), c0..c3, on the "
          "scaled x recorded in meta.json"),
    field("n_min", pa.uint16(), "LSB2", "minimum valid second-stage code Nmin (sec. 3.2)"),
    field("n_max", pa.uint16(), "LSB2", "maximum valid second-stage code Nmax"),
    field("n_th", pa.uint16(), "LSB2", "minimum D2nd when P1st = 0 (Nth, eq. 3.4)"),
    field("pdm", pa.uint16(), "LSB2", "minimum D2nd when P1st = 4 (PDM, eq. 3.4)"),
    field("delay_ps", pa.float64(), "ps", "system delay T_delay (eq. 5.3)", nullable=True),
    # 1.1: the density test's verdict per TDC
    field("ok", pa.bool_(), "", "false for a dead or dark TDC (flagged, excluded)"),
))

CALIBRATION_INL = SchemaSpec("calibration_inl", "1.1", (
    field("tdc", pa.uint16(), "", "TDC address (0-based)"),
    field("code", pa.uint16(), "LSB", "first-stage code D1st"),
    field("width_lsb", pa.float64(), "LSB", "code bin width from the density test"),
    field("dnl_lsb", pa.float64(), "LSB", "differential non-linearity"),
    field("inl_lsb", pa.float64(), "LSB", "integral non-linearity"),
    # 1.1: the calibration's own uncertainty (issue 33.3); 1.0 files lack it
    field("width_sigma_lsb", pa.float64(), "LSB", "standard error of width_lsb from the "
          "calibration's counts (the density tests' combined; where no test measured the "
          "code, the random DNL about the phase pattern); null where not known",
          nullable=True),
))

RANGES = SchemaSpec("ranges", "3.0", (
    field("measurement", pa.string(), "", "name of the measurement"),
    # 3.0: uint32 (a generic file's pixel numbers up to 2^32 - 1, issue 34.7; it was uint16)
    field("tdc", pa.uint32(), "", "TDC address (0-based); for generic histograms the "
          "file's row number, 0..2^32 - 1"),
    field("distance_m", pa.float64(), "m", "estimated distance (eq. 5.4); on a row not "
          "detected the best candidate's (or NaN), not a return: `detected` tells them "
          "apart, and `tcspc export` writes detected returns only"),
    field("sigma_m", pa.float64(), "m", "one-sigma uncertainty of distance_m: the fit's "
          "(its counts' Fisher information) and, ranged with a chip calibration that stores "
          "its own uncertainty (docs/calibration.md), the calibration's in quadrature: the "
          "code widths' counting noise over the codes between this return and the delay's "
          "zero-distance return, the delay's peak fit and the time scale's interpolation "
          "between the density tests' lights; generic histograms ranged with a "
          "calibration from `calibrate distance`: its row's line (delay and bin width, from "
          "the calibration returns' sigmas) in quadrature; the fit's alone otherwise (an "
          "instrument's file, generic histograms with --delay-ps or --zero, a calibration "
          "made before issue 33 or, for generic histograms, before issue 34)"),
    field("fwhm_m", pa.float64(), "m", "measured FWHM of the return: the second moment of "
          "its pile-up-corrected counts above the background (NaN: none above it); 1.0 "
          "files carry the instrument response's FWHM here"),
    field("signal_counts", pa.float64(), "count", "estimated signal detections"),
    field("background_per_bin", pa.float64(), "count", "estimated background per code"),
    field("detected", pa.bool_(), "", "detection decision at the stated false-alarm rate"),
    field("estimator", pa.string(), "", "name of the estimator"),
    # 2.0: more than one surface a pixel, and why a row is flagged
    field("return_index", pa.uint8(), "", "the return's rank in its pixel by signal counts "
          "(0 the strongest; the spatial estimator's 0 is the surface its neighbours hold "
          "where its own lone detection is weaker, docs/ranging.md; every TDC has a row 0, "
          "detected or not, and a row k > 0 only for a detected return)"),
    field("flag", pa.string(), "", "empty, or why the row is flagged (several joined by "
          "'; '): an input it could not use, an estimate outside the window or before the "
          "zero, the window's edge, another chip's calibration, a partial measurement (the "
          "stream ended inside it)"),
))

#: The major versions of ``ranges`` this software reads: 1.x (one row a TDC, no
#: return_index or flag) and 2.x (``tdc`` uint16) are upgraded on read by
#: :func:`pipeline.io.ranges.read_ranges`.
RANGES_READS = (1, 2, 3)
