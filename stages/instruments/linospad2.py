"""LinoSPAD2 raw TDC words: decoding, fine-code histograms and a code-density calibration.

Pure and vectorised (no loop per word, no file IO: ``pipeline.io.linospad2`` reads files).

The format (firmware 2212b/2212s; read from the daplis and daplis-rtp unpackers of the board's
authors, rewritten here from the description):

- little-endian uint32 words; one acquisition cycle is ``LINES = 65`` TDC lines of
  ``words_per_line`` words (200 in the sample capture; the firmware's setting, 512 by
  default in daplis, so it is a parameter here);
- bit 31: valid. In each line the valid words come first, then padding (all-zero words in
  the sample); bits 29:28: which of the TDC's 4 pixels fired; bits 27:0: the time code in
  units of ``CODE_PS`` (2.5 ns / 140 = 17.857 ps) since the cycle's start, so
  ``code // 140`` counts 400 MHz clock periods and ``code % 140`` is the carry chain's fine
  code;
- lines 0..63 are TDCs 0..63; line 64 (the 65th) carries no pixel data (in the sample: one
  valid word with pixel bits 01 and a small code, 353..355, then padding). Its words are
  counted, never decoded as photons;
- the pixel of a word: ``4 * tdc + bits`` for 2212b ("block": a TDC serves 4 neighbours),
  ``tdc + 64 * bits`` for 2212s ("skip": a TDC serves pixels 64 apart);
- bit 30 is not documented by daplis; in the sample it equals bit 31 in every word, so
  nothing here relies on it.

Firmware 2208 is not supported: its cycle is 256 lines (one per pixel) of words without
pixel bits and without a 65th line, so it is a different framing, not a different pixel map,
and there is no sample capture to test it against.

Every word is accounted for (:class:`Tally`): ``valid + invalid + line65 == words``.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Literal

import numpy as np

#: words per TDC line in the sample capture (firmware setting; daplis' default is 512)
WORDS_PER_LINE = 200
#: lines per acquisition cycle: 64 TDCs and the 65th line without pixel data
LINES = 65
N_TDC = 64
N_PIXEL = 256
PIXELS_PER_TDC = 4
#: carry-chain (fine) codes per 2.5 ns clock period
N_FINE = 140
CLOCK_PS = 2500.0
#: one time code: 2.5 ns / 140 = 17.857 ps
CODE_PS = CLOCK_PS / N_FINE
VALID_BIT = np.uint32(1 << 31)
PIXEL_SHIFT = np.uint32(28)
CODE_MASK = np.uint32(0x0FFF_FFFF)
#: the firmware revisions decoded here (their pixel maps differ; see the module docstring)
Firmware = Literal["2212b", "2212s"]
FIRMWARES: tuple[Firmware, ...] = ("2212b", "2212s")
#: conventions for the time of a fine code within the clock period (see :class:`CodeDensity`)
CONVENTIONS = ("lower", "centre", "upper")


def check_firmware(firmware: str) -> str:
    """Return ``firmware`` if supported, else raise ``ValueError`` saying why.

    >>> check_firmware("2212s")
    '2212s'
    """
    if firmware in FIRMWARES:
        return firmware
    if firmware == "2208":
        raise ValueError("LinoSPAD2 firmware '2208' is not supported: its cycle is 256 lines "
                         "(one per pixel, no pixel bits, no 65th line), a different framing "
                         f"from {FIRMWARES}")
    raise ValueError(f"unknown LinoSPAD2 firmware {firmware!r}; expected one of {FIRMWARES}")


def pixel_of(tdc, bits, firmware: str) -> np.ndarray:
    """Pixel (0..255) of the TDC and the word's pixel bits (0..3).

    >>> pixel_of([0, 1, 63], [3, 0, 3], "2212b").tolist()
    [3, 4, 255]
    >>> pixel_of([0, 1, 63], [3, 0, 3], "2212s").tolist()
    [192, 1, 255]
    """
    check_firmware(firmware)
    tdc = np.asarray(tdc).astype(np.uint16)
    bits = np.asarray(bits).astype(np.uint16)
    if firmware == "2212b":
        return tdc * np.uint16(PIXELS_PER_TDC) + bits
    return tdc + np.uint16(N_TDC) * bits


def tdc_of(pixel, firmware: str) -> np.ndarray:
    """TDC (0..63) that serves ``pixel``: the inverse of :func:`pixel_of` (with the bits).

    >>> tdc_of([3, 4, 192], "2212b").tolist(), tdc_of([3, 4, 192], "2212s").tolist()
    ([0, 1, 48], [3, 4, 0])
    """
    check_firmware(firmware)
    pixel = np.asarray(pixel).astype(np.int64)
    return (pixel // PIXELS_PER_TDC if firmware == "2212b" else pixel % N_TDC).astype(np.uint8)


# --------------------------------------------------------------------------- accounting

@dataclass(frozen=True)
class Tally:
    """Where every word (and every byte of a file) went. Tallies of chunks add.

    ``valid``: photon words of the 64 TDC lines; ``invalid``: padding words of those lines
    (bit 31 clear); ``line65``: every word of the 65th line, of which ``line65_valid`` had
    bit 31 set; ``truncated_bytes``: bytes after the last whole cycle of a file (set by
    the file reader; a chunk of words never has any).
    """

    cycles: int = 0
    words: int = 0
    valid: int = 0
    invalid: int = 0
    line65: int = 0
    line65_valid: int = 0
    truncated_bytes: int = 0

    def __add__(self, other: Tally) -> Tally:
        return Tally(**{f.name: getattr(self, f.name) + getattr(other, f.name)
                        for f in fields(self)})

    @property
    def accounted(self) -> bool:
        """``valid + invalid + line65 == words`` (always, unless built by hand)."""
        return self.valid + self.invalid + self.line65 == self.words

    @property
    def truncated(self) -> bool:
        return self.truncated_bytes > 0

    def to_dict(self) -> dict:
        return {f.name: int(getattr(self, f.name)) for f in fields(self)}


def _cycles_view(words, words_per_line: int) -> np.ndarray:
    """``words`` as (cycles, 65, words_per_line) uint32, refusing a partial cycle."""
    w = np.asarray(words)
    if w.dtype.kind not in "ui":
        raise ValueError(f"LinoSPAD2 words must be unsigned 32-bit integers, found {w.dtype}")
    if w.dtype != np.uint32:
        if w.size and (w.min() < 0 or w.max() > 0xFFFF_FFFF):
            raise ValueError("LinoSPAD2 words must fit in 32 bits")
        w = w.astype(np.uint32)
    if words_per_line < 1:
        raise ValueError(f"words_per_line must be >= 1, found {words_per_line}")
    per_cycle = LINES * words_per_line
    if w.size % per_cycle:
        raise ValueError(f"{w.size} words are not a whole number of cycles of {LINES} lines x "
                         f"{words_per_line} words ({per_cycle} words): "
                         f"{w.size // per_cycle} cycles and {w.size % per_cycle} words over")
    return w.reshape(-1, LINES, words_per_line)


def _tally(c: np.ndarray, valid: np.ndarray) -> Tally:
    """The accounting of a (cycles, 65, wpl) block whose pixel-line validity is ``valid``."""
    n_valid = int(np.count_nonzero(valid))
    line65 = c[:, LINES - 1, :]
    return Tally(cycles=int(c.shape[0]), words=int(c.size), valid=n_valid,
                 invalid=int(valid.size) - n_valid, line65=int(line65.size),
                 line65_valid=int(np.count_nonzero(line65 & VALID_BIT)))


# ------------------------------------------------------------------------------ decoding

@dataclass(frozen=True)
class Decoded:
    """Valid photon words of whole cycles, in file order (cycle, then TDC, then slot)."""

    cycle: np.ndarray   #: uint32, 0-based in the file (``first_cycle`` added)
    tdc: np.ndarray     #: uint8
    pixel: np.ndarray   #: uint16
    code: np.ndarray    #: uint32, bits 27:0 (17.857 ps units since the cycle's start)
    fine: np.ndarray    #: uint8, code % 140
    tally: Tally

    def __len__(self) -> int:
        return int(self.code.size)

    def columns(self) -> dict[str, np.ndarray]:
        """The columns of ``schemas.instruments.LINOSPAD2_EVENTS``, by name."""
        return {"cycle": self.cycle, "tdc": self.tdc, "pixel": self.pixel,
                "code": self.code, "fine": self.fine}


def decode_words(words, firmware: str, words_per_line: int = WORDS_PER_LINE,
                 first_cycle: int = 0) -> Decoded:
    """Decode the valid photon words of whole cycles.

    Parameters
    ----------
    words : array of uint32 (native byte order), a whole number of cycles.
    firmware : "2212b" or "2212s" (the pixel map).
    words_per_line : the capture's words per TDC line.
    first_cycle : index in the file of the first cycle of ``words`` (for chunks).

    Examples
    --------
    >>> w = np.zeros(LINES * 2, np.uint32)       # one cycle of 2 words per line
    >>> w[2 * 5] = VALID_BIT | (3 << 28) | 141   # TDC 5, pixel bits 3, code 141
    >>> d = decode_words(w, "2212b", words_per_line=2)
    >>> d.tdc.tolist(), d.pixel.tolist(), d.code.tolist(), d.fine.tolist()
    ([5], [23], [141], [1])
    >>> d.tally.valid, d.tally.invalid, d.tally.line65, d.tally.accounted
    (1, 127, 2, True)
    """
    check_firmware(firmware)
    c = _cycles_view(words, words_per_line)
    px = c[:, : LINES - 1, :]
    valid = (px & VALID_BIT) != 0
    cyc, tdc, _ = np.nonzero(valid)            # file order: C order of (cycle, tdc, slot)
    vw = px[valid]
    code = vw & CODE_MASK
    bits = (vw >> PIXEL_SHIFT) & np.uint32(3)
    return Decoded(
        cycle=(cyc + first_cycle).astype(np.uint32),
        tdc=tdc.astype(np.uint8),
        pixel=pixel_of(tdc, bits, firmware),
        code=code.astype(np.uint32),
        fine=(code % np.uint32(N_FINE)).astype(np.uint8),
        tally=_tally(c, valid),
    )


def fine_histograms(words, firmware: str, by: str = "pixel",
                    words_per_line: int = WORDS_PER_LINE) -> tuple[np.ndarray, Tally]:
    """Counts of each fine code, per TDC (64, 140) or per pixel (256, 140), and the tally.

    Works on any chunk of whole cycles; the counts and tallies of chunks add up to those of
    the whole (``tests/stages/test_linospad2.py`` checks it over random splits).

    >>> w = np.zeros(LINES * 2, np.uint32)
    >>> w[[0, 1]] = VALID_BIT | np.array([139, 280], np.uint32)   # TDC 0, pixel 0
    >>> counts, tally = fine_histograms(w, "2212b", by="tdc", words_per_line=2)
    >>> counts.shape, counts.dtype, counts[0, [0, 139]].tolist(), tally.valid
    ((64, 140), dtype('uint64'), [1, 1], 2)
    """
    check_firmware(firmware)
    if by not in ("tdc", "pixel"):
        raise ValueError(f"fine_histograms: by must be 'tdc' or 'pixel', found {by!r}")
    c = _cycles_view(words, words_per_line)
    px = c[:, : LINES - 1, :]
    valid = (px & VALID_BIT) != 0
    vw = px[valid]
    fine = ((vw & CODE_MASK) % np.uint32(N_FINE)).astype(np.int64)
    tdc = np.broadcast_to(np.arange(N_TDC, dtype=np.int64)[None, :, None], px.shape)[valid]
    if by == "tdc":
        row, n_rows = tdc, N_TDC
    else:
        bits = ((vw >> PIXEL_SHIFT) & np.uint32(3)).astype(np.int64)
        row, n_rows = pixel_of(tdc, bits, firmware).astype(np.int64), N_PIXEL
    counts = np.bincount(row * N_FINE + fine, minlength=n_rows * N_FINE)
    return counts.reshape(n_rows, N_FINE).astype(np.uint64), _tally(c, valid)


# ------------------------------------------------------------- times of flight (a laser)

def photon_times_ps(code, row, table_ps=None) -> np.ndarray:
    """Each photon's time since its cycle's start, ps (float64).

    ``code`` the words' 28-bit codes, ``row`` each photon's row of ``table_ps`` (its pixel
    for a per-pixel table, its TDC for a per-TDC one). The clock period ``code // 140`` counts
    2.5 ns; within it the fine code's time is nominal (``fine x 17.857 ps``: the carry chain
    taken as linear, which it is not: ~20 % of its codes are dead and the rest ~21 ps wide,
    see docs/instruments_linospad2.md) or, given a code-density table (rows x 140
    cumulative code times, ps, each code's upper edge: the published convention,
    :class:`CodeDensity`), the centre of the code's calibrated interval.

    >>> photon_times_ps(np.array([141, 2 * 140 + 3]), np.array([0, 0])).round(3).tolist()
    [2517.857, 5053.571]
    >>> tab = np.tile(np.linspace(0, 2500, 141)[1:], (1, 1))   # 140 codes of 17.857 ps
    >>> photon_times_ps(np.array([141]), np.array([0]), tab).round(3).tolist()
    [2526.786]
    """
    code = np.asarray(code, np.int64)
    coarse = (code // N_FINE).astype(np.float64) * CLOCK_PS
    fine = code % N_FINE
    if table_ps is None:
        return coarse + fine * CODE_PS
    tab = np.asarray(table_ps, np.float64)
    if tab.ndim != 2 or tab.shape[1] != N_FINE:
        raise ValueError(f"photon_times_ps: a table of rows x {N_FINE} code times, found "
                         f"{tab.shape}")
    upper = tab[np.asarray(row, np.int64), fine]
    lower = np.where(fine > 0, tab[np.asarray(row, np.int64), np.maximum(fine - 1, 0)], 0.0)
    return coarse + 0.5 * (lower + upper)


def folded_histograms(row, t_ps, n_rows: int, period_ps: float, bins: int) -> np.ndarray:
    """Counts (n_rows, bins) int64 of the times folded on a laser period: ``t mod period``
    in ``bins`` bins of ``period / bins`` (a laser fired by the board's clock, so that
    its pulses fall at multiples of the period since each cycle's start).

    >>> folded_histograms([0, 0, 1], [10.0, 110.0, 205.0], 2, 100.0, 4).tolist()
    [[2, 0, 0, 0], [1, 0, 0, 0]]
    """
    if not (np.isfinite(period_ps) and period_ps > 0):
        raise ValueError(f"folded_histograms: the period must be > 0 ps, found {period_ps}")
    if bins < 1:
        raise ValueError(f"folded_histograms: bins must be >= 1, found {bins}")
    row = np.asarray(row, np.int64)
    b = np.floor(np.mod(np.asarray(t_ps, np.float64), period_ps) * (bins / period_ps))
    b = np.minimum(b.astype(np.int64), bins - 1)      # (a rounding at the period's end)
    return np.bincount(row * bins + b, minlength=n_rows * bins).reshape(n_rows, bins)


# ------------------------------------------------------------------------- code density

@dataclass(frozen=True)
class CodeDensity:
    """Code-density calibration of 140-code carry chains (one row per TDC or pixel).

    Under light uncorrelated with the 400 MHz clock, a fine code's share of the hits is its
    width's share of the 2.5 ns period: ``width_k = hits_k / sum(hits) * 2500 ps``. No
    pile-up correction is needed (unlike ``stages.calibration.density_test`` for the thesis
    chip's window-long first stage): the fine code is the phase within a clock period, and
    the capture spans ~10^5 periods, so dead time and pile-up act on the period number, not
    on the phase. Codes with no hits have width 0 (dead codes: the chain's first ~15-27
    codes never occur).

    The time of code k within the period, ``code_time_ps(convention)``:
    ``"lower"``: the sum of the widths below k; ``"centre"``: that plus half of width_k;
    ``"upper"``: the sum of the widths up to and including k. ``"upper"`` is the convention
    of the board's published tables (daplis writes ``cumsum(counts) / total * 2500``, and
    the last code of every live row is exactly 2500 ps).
    """

    counts: np.ndarray   #: (n, 140) uint64
    hits: np.ndarray     #: (n,) int64
    width_ps: np.ndarray  #: (n, 140) float64; NaN for a row without hits

    @property
    def lower_ps(self) -> np.ndarray:
        return self.upper_ps - self.width_ps

    @property
    def upper_ps(self) -> np.ndarray:
        return np.cumsum(self.width_ps, axis=1)

    @property
    def centre_ps(self) -> np.ndarray:
        return self.upper_ps - 0.5 * self.width_ps

    def code_time_ps(self, convention: str = "upper") -> np.ndarray:
        """(n, 140) time of each code within the clock period, in the given convention."""
        if convention not in CONVENTIONS:
            raise ValueError(f"convention must be one of {CONVENTIONS}, found {convention!r}")
        return getattr(self, f"{convention}_ps")

    @property
    def dead(self) -> np.ndarray:
        """(n, 140) codes without a hit."""
        return self.counts == 0

    @property
    def dnl_lsb(self) -> np.ndarray:
        """Width over the nominal 17.857 ps, less 1."""
        return self.width_ps / CODE_PS - 1.0

    @property
    def inl_lsb(self) -> np.ndarray:
        """Each code's upper edge against the ideal one, (k + 1) x 17.857 ps, in codes."""
        return self.upper_ps / CODE_PS - np.arange(1, N_FINE + 1)

    def sigma_ps(self, convention: str = "upper") -> np.ndarray:
        """Binomial standard error of ``code_time_ps(convention)``: the share F of hits
        below that point is binomial, so ``sqrt(F (1 - F) / N) x 2500 ps``."""
        f = np.clip(self.code_time_ps(convention) / CLOCK_PS, 0.0, 1.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.sqrt(f * (1 - f) / self.hits[:, None]) * CLOCK_PS


def code_density(counts) -> CodeDensity:
    """Code widths (ps) from (n, 140) fine-code counts of uniform light.

    >>> cd = code_density(np.array([[0, 1, 3] + [0] * 137]))
    >>> cd.width_ps[0, :3].tolist(), cd.upper_ps[0, [0, 1, 2, 139]].tolist()
    ([0.0, 625.0, 1875.0], [0.0, 625.0, 2500.0, 2500.0])
    >>> float(cd.centre_ps[0, 1]), float(cd.lower_ps[0, 2])
    (312.5, 625.0)
    """
    counts = np.asarray(counts)
    if counts.ndim != 2 or counts.shape[1] != N_FINE:
        raise ValueError(f"code_density: counts must be (n, {N_FINE}), found {counts.shape}")
    if counts.dtype.kind not in "ui" or (counts.size and counts.min() < 0):
        raise ValueError("code_density: counts must be non-negative integers")
    counts = counts.astype(np.uint64)
    hits = counts.sum(axis=1, dtype=np.uint64).astype(np.int64)
    with np.errstate(invalid="ignore", divide="ignore"):
        width = counts.astype(np.float64) / hits[:, None] * CLOCK_PS
    return CodeDensity(counts=counts, hits=hits, width_ps=width)


def counts_from_cumulative(table_ps, max_multiple: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """The integer hit counts behind cumulative code-time rows (``"upper"`` convention).

    A published row is ``cumsum(counts) / N x 2500``: its widths are multiples of
    ``2500 / N``. The smallest positive width is ``m x 2500 / N`` for a small m (1 unless
    every count is a multiple of m); the first m in 1..``max_multiple`` that makes every
    width a whole number of hits (to 1e-6) gives N and the counts. Rows that are not such
    a histogram (an average of several, all zero) get counts -1 and N = 0.

    >>> counts, n = counts_from_cumulative([[0.0, 625.0, 2500.0] + [2500.0] * 137])
    >>> counts[0, :3].tolist(), n.tolist()
    ([0, 1, 3], [4])
    """
    t = np.asarray(table_ps, np.float64)
    if t.ndim != 2:
        raise ValueError(f"counts_from_cumulative: table must be 2-D, found {t.shape}")
    w = np.diff(t, axis=1, prepend=0.0)
    pos = np.where(w > 1e-9, w, np.inf)
    wmin = pos.min(axis=1)
    n_out = np.zeros(t.shape[0], np.int64)
    counts = np.full(t.shape, -1, np.int64)
    live = np.isfinite(wmin) & (np.abs(t[:, -1] - CLOCK_PS) < 1e-6 * CLOCK_PS)
    for m in range(1, max_multiple + 1):  # a handful of candidates, each over every row
        with np.errstate(invalid="ignore", divide="ignore"):
            n = np.round(m * CLOCK_PS / wmin)
            c = w * n[:, None] / CLOCK_PS
        whole = np.all(np.abs(c - np.round(c)) < 1e-6 * np.maximum(1.0, np.abs(c)), axis=1)
        take = live & whole & (n_out == 0)
        n_out[take] = n[take].astype(np.int64)
        counts[take] = np.round(c[take]).astype(np.int64)
    return counts, n_out


# ------------------------------------------------------- comparison with a published table

@dataclass(frozen=True)
class Comparison:
    """Measured code times against a published table, one value per row (pixel or TDC).

    ``rms_ps``/``max_ps``/``mean_ps``: RMS, largest absolute and mean difference (measured
    - published) over the 140 codes. ``expected_rms_ps``: the RMS that binomial statistics
    alone give, both tables being code-density tests of N and N_pub hits:
    ``sqrt(mean_k F_k (1 - F_k) x (1/N + 1/N_pub)) x 2500 ps`` with F_k the pooled share of
    hits up to code k; ``expected_rms_own_ps``: the same with this capture's statistics only
    (1/N), the floor if the published table were exact. ``p_value``: the share of Monte
    Carlo pairs of captures with the same N and N_pub, drawn from the pooled widths, whose
    RMS over their expectation is at least the measured one (NaN without draws). The codes
    are strongly correlated (a cumulative sum), so the ratio's spread is wide: its median
    under pure statistics is ~0.84, not 1, and ~1.5 % of pixels exceed 2.
    """

    rms_ps: np.ndarray
    max_ps: np.ndarray
    mean_ps: np.ndarray
    expected_rms_ps: np.ndarray
    expected_rms_own_ps: np.ndarray
    hits: np.ndarray             #: this capture's hits per row
    published_hits: np.ndarray   #: hits behind the published row (0 if not a histogram)
    dead_codes: np.ndarray       #: codes without a hit in this capture
    published_dead_codes: np.ndarray  #: zero-width codes of the published row
    dead_in_both: np.ndarray     #: codes without a hit in either: dead as far as both know
    p_value: np.ndarray
    null_ratio: np.ndarray       #: (draws, rows) RMS / expected of the draws (NaN: none)

    @property
    def live(self) -> np.ndarray:
        """Rows with hits in both tables."""
        return (self.hits > 0) & np.isfinite(self.rms_ps)

    @property
    def ratio(self) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.rms_ps / self.expected_rms_ps


def _rms_expected(f_pooled: np.ndarray, inv_n: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(np.mean(f_pooled * (1 - f_pooled), axis=1) * inv_n) * CLOCK_PS


def compare_code_times(counts, published_ps, convention: str = "upper",
                       published_counts=None, rng: np.random.Generator | None = None,
                       n_null: int = 0) -> Comparison:
    """Compare a capture's fine-code counts with a published cumulative code-time table.

    Parameters
    ----------
    counts : (n, 140) this capture's counts.
    published_ps : (n, 140) published code times (``"upper"`` convention: cumulative).
    convention : the convention the measured code times are taken in (``"upper"`` matches
        the published tables; the others show what a convention mismatch costs).
    published_counts : (n, 140) the hits behind the published rows, if known; else they
        are reconstructed with :func:`counts_from_cumulative` (rows that are not a
        histogram are compared with this capture's statistics only).
    rng, n_null : Monte Carlo draws of the null hypothesis (same widths, binomial
        statistics) for ``p_value``; ``rng`` is required when ``n_null > 0``.
    """
    pub = np.asarray(published_ps, np.float64)
    mine = code_density(counts)
    if pub.shape != mine.width_ps.shape:
        raise ValueError(f"compare_code_times: published table {pub.shape} does not match "
                         f"the counts {mine.width_ps.shape}")
    if published_counts is None:
        pc, n_pub = counts_from_cumulative(pub)
    else:
        pc = np.asarray(published_counts, np.int64)
        n_pub = pc.sum(axis=1)
    known = n_pub > 0
    pc = np.where(known[:, None], pc, 0)
    pub_live = pub[:, -1] > 0
    live = (mine.hits > 0) & pub_live
    diff = np.where(live[:, None], mine.code_time_ps(convention) - pub, np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(np.mean(diff ** 2, axis=1))
        # the pooled F: both histograms where the published one is known, else ours
        f_pool = np.where(known[:, None],
                          np.cumsum(mine.counts.astype(np.float64) + pc, axis=1)
                          / (mine.hits + n_pub)[:, None],
                          mine.upper_ps / CLOCK_PS)
        inv_own = 1.0 / mine.hits
        inv_both = inv_own + np.where(known, 1.0 / np.maximum(n_pub, 1), 0.0)
    expected = np.where(live, _rms_expected(f_pool, inv_both), np.nan)
    expected_own = np.where(live, _rms_expected(f_pool, inv_own), np.nan)
    p_value = np.full(rms.shape, np.nan)
    null = np.full((0, rms.size), np.nan)
    if n_null > 0:
        if rng is None:
            raise ValueError("compare_code_times: n_null > 0 needs an rng (numpy Generator)")
        null = _null_ratios(mine.counts, pc, live & known, rng, n_null)
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = rms / expected
            exceed = np.sum(null >= ratio[None, :], axis=0)
        p_value = np.where(live & known, (exceed + 1.0) / (n_null + 1.0), np.nan)
    absdiff = np.abs(diff)  # NaN outside the live rows
    return Comparison(
        rms_ps=rms,
        max_ps=np.where(live, np.max(np.where(live[:, None], absdiff, 0.0), axis=1), np.nan),
        mean_ps=np.mean(diff, axis=1),
        expected_rms_ps=expected,
        expected_rms_own_ps=expected_own,
        hits=mine.hits,
        published_hits=n_pub,
        dead_codes=np.sum(mine.dead, axis=1),
        published_dead_codes=np.where(pub_live, np.sum(np.diff(pub, axis=1, prepend=0.0)
                                                       <= 1e-9, axis=1), N_FINE),
        dead_in_both=np.where(known, np.sum(mine.dead & (pc == 0), axis=1), -1),
        p_value=p_value,
        null_ratio=null,
    )


def pool_by_tdc(counts, firmware: str) -> np.ndarray:
    """(64, 140) counts of the 4 pixels of each TDC summed, from (256, 140) per pixel.

    >>> c = np.zeros((256, 140), np.int64); c[[0, 1, 64], 5] = 1
    >>> int(pool_by_tdc(c, "2212b")[0, 5]), int(pool_by_tdc(c, "2212s")[0, 5])
    (2, 2)
    """
    counts = np.asarray(counts, np.int64)
    if counts.shape != (N_PIXEL, N_FINE):
        raise ValueError(f"pool_by_tdc: counts must be (256, 140), found {counts.shape}")
    pooled = np.zeros((N_TDC, N_FINE), np.int64)
    np.add.at(pooled, tdc_of(np.arange(N_PIXEL), firmware).astype(np.int64), counts)
    return pooled


def pixels_against_their_tdc(counts, firmware: str, rng: np.random.Generator | None = None,
                             n_null: int = 0) -> Comparison:
    """Each pixel's code times against the other 3 pixels of its TDC pooled (one capture).

    The 4 pixels of a TDC share its carry chain, so their tables should differ by
    statistics only (ratio ~ the Monte Carlo null's); TDCs against each other should not.
    """
    counts = np.asarray(counts, np.int64)
    pooled = pool_by_tdc(counts, firmware)
    others = pooled[tdc_of(np.arange(N_PIXEL), firmware).astype(np.int64)] - counts
    with np.errstate(invalid="ignore", divide="ignore"):
        ref = np.nan_to_num(code_density(others).upper_ps)
    return compare_code_times(counts, ref, published_counts=others, rng=rng, n_null=n_null)


def _null_ratios(counts, published_counts, rows, rng, n_null: int) -> np.ndarray:
    """(n_null, n) RMS / expected of pairs of multinomial captures with the same hits as
    the two tables, drawn from their pooled widths (NaN outside ``rows``)."""
    a = np.asarray(counts, np.int64)[rows]
    b = np.asarray(published_counts, np.int64)[rows]
    na, nb = a.sum(axis=1), b.sum(axis=1)
    p = (a + b) / (na + nb)[:, None]
    out = np.full((n_null, rows.size), np.nan)
    for i in range(n_null):  # one draw of every row at once per iteration
        fa = np.cumsum(rng.multinomial(na, p), axis=1) / na[:, None]
        fb = np.cumsum(rng.multinomial(nb, p), axis=1) / nb[:, None]
        exp = _rms_expected((fa * na[:, None] + fb * nb[:, None]) / (na + nb)[:, None],
                            1.0 / na + 1.0 / nb)
        with np.errstate(invalid="ignore", divide="ignore"):
            out[i, rows] = np.sqrt(np.mean((fa - fb) ** 2, axis=1)) * CLOCK_PS / exp
    return out


# ------------------------------------------------------------------ synthetic captures

def simulate_words(width_ps, cycles: int, rng: np.random.Generator, firmware: str = "2212b",
                   words_per_line: int = WORDS_PER_LINE, fill: float = 0.5,
                   mean_gap_periods: int = 400) -> np.ndarray:
    """Words of a uniform-light capture whose chains have the given code widths.

    ``width_ps``: (256, 140) per pixel or (64, 140) per TDC (each row sums to 2500). Each
    TDC line holds a binomial(words_per_line, ``fill``) number of hits, valid words first,
    codes increasing (clock periods ``1..2 x mean_gap_periods`` apart), pixel bits uniform,
    fine codes drawn from the row's widths; bit 30 mirrors bit 31 as in the sample capture;
    the 65th line holds one valid word (pixel bits 01, code 354) then padding, as there.

    >>> w = simulate_words(np.full((64, 140), CODE_PS), 2, np.random.default_rng(0),
    ...                    words_per_line=8)
    >>> t = decode_words(w, "2212b", words_per_line=8).tally
    >>> t.accounted, t.line65_valid, t.words == 2 * LINES * 8
    (True, 2, True)
    """
    check_firmware(firmware)
    width = np.asarray(width_ps, np.float64)
    if width.shape not in ((N_PIXEL, N_FINE), (N_TDC, N_FINE)):
        raise ValueError(f"simulate_words: widths must be (256 or 64, 140), found {width.shape}")
    cdf = np.cumsum(width, axis=1) / width.sum(axis=1, keepdims=True)
    shape = (cycles, N_TDC, words_per_line)
    n_hits = rng.binomial(words_per_line, fill, size=shape[:2])
    valid = np.arange(words_per_line)[None, None, :] < n_hits[..., None]
    period = np.cumsum(rng.integers(1, 2 * mean_gap_periods, size=shape), axis=2)
    bits = rng.integers(0, PIXELS_PER_TDC, size=shape)
    tdc = np.broadcast_to(np.arange(N_TDC)[None, :, None], shape)
    row = pixel_of(tdc, bits, firmware).astype(np.int64) if width.shape[0] == N_PIXEL else tdc
    u = rng.random(shape)
    fine = np.zeros(shape, np.int64)
    for k in range(N_FINE - 1):  # inverse CDF, one comparison per code (140), not per word
        fine += u >= cdf[row, k]
    code = period * N_FINE + fine
    if code.max(initial=0) > int(CODE_MASK):
        raise ValueError("simulate_words: codes overflow 28 bits; fewer words or periods")
    pixel_words = np.where(valid, (np.uint32(3 << 30) | (bits.astype(np.uint32) << PIXEL_SHIFT)
                                   | code.astype(np.uint32)), np.uint32(0))
    out = np.zeros((cycles, LINES, words_per_line), np.uint32)
    out[:, : LINES - 1] = pixel_words
    out[:, LINES - 1, 0] = np.uint32(3 << 30) | np.uint32(1 << 28) | np.uint32(354)
    return out.ravel()
