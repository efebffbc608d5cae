"""PicoQuant TTTR records (the data section of a PTU file): pure decoders of every record type.

A record is one little-endian uint32. Two bit layouts cover every record type PicoQuant
publishes (``doc/apx_tttrrecords.html`` and ``Read_PTU.py`` of
PicoQuant/PicoQuant-Time-Tagged-File-Format-Demos); bits are given from the MSB:

``picoharp`` (PicoHarp 300)
    channel 4 | T3: dtime 12, nsync 16 | T2: timetag 28.
    Channel 15 is special. T3: dtime 0 is an overflow (one wrap of 65536 syncs), dtime
    1..15 are marker bits. T2: the low 4 bits of the timetag are the marker bits, 0 is an
    overflow (one wrap of 210698240 timetag units).
    Other channels: T3 channel 1..4 is the (router) input 1..4; T2 channel 0 is the sync
    input and 1..4 the inputs 1..4.
``hydraharp`` (HydraHarp V1/V2, TimeHarp 260 N/P, MultiHarp, PicoHarp 330)
    special 1 | channel 6 | T3: dtime 15, nsync 10 | T2: timetag 25.
    Special with channel 63 is an overflow: one wrap for HydraHarp V1 (1024 syncs in T3,
    33552000 units in T2), and for every later type ``nsync`` / ``timetag`` wraps (1024 /
    33554432 each; a count of 0 means one, the old-style overflow). Special with channel
    1..15 carries marker bits. T2 only: special with channel 0 is a sync event.
    Regular records: channel 0..63 is input 1..64.

What this module returns, for every layout:

- a photon: ``kind = PHOTON`` and ``channel`` the 0-based input (input 1 is channel 0);
- a marker: ``kind = MARKER`` and ``channel`` the marker bits (1..15), ``dtime`` 0;
- a sync event (T2 only): ``kind = PHOTON`` on :data:`SYNC_CHANNEL` (64, beyond the 64
  inputs a record can address). In T2 mode the sync input is timed like any input
  (PicoHarp 300 records it as channel 0), so it is an event on a channel of its own; it is
  counted apart from the photons (``n_sync``) and a photon filter must exclude the channel;
- an overflow record adds its wraps to the running count and is counted, not returned;
- a record that fits no rule (PicoHarp channel 0 in T3 or 5..14, a marker field above
  15, HydraHarp special channels 16..62, special channel 0 in T3) is counted in
  ``n_invalid``, not returned.

Every record lands in exactly one counter: photons + syncs + markers + overflow records +
invalid = records.

Time is exact integer arithmetic: T3 ``time`` is the sync number ``wraps * wrap + nsync``
(uint64), T2 ``time`` the timetag ``wraps * wrap + timetag`` (int64) in the file's
resolution. Decoding a stream chunk by chunk, passing each chunk's ``wraps`` into the
next, gives exactly what decoding it at once gives.

Two engines compute the same thing and are tested to agree on every record type: numba
(one compiled loop per layout and mode, loaded as a C kernel without numba where it can
be, see ``_native``) and numpy (vectorised masks and a cumulative sum of
the wraps), the fallback where numba is missing.
"""

from __future__ import annotations

import ctypes
import importlib.util
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from schemas.instruments import MARKER, PHOTON

# numba is a dependency, but the numpy path must work (and is tested) without it; it is
# imported only where a kernel must be compiled (stages.nativecode loads them without it)
HAVE_NUMBA = importlib.util.find_spec("numba") is not None

ENGINES = ("numba", "numpy")
#: ``channel`` of a T2 sync event (``kind`` PHOTON): one past the 64 inputs of the
#: hydraharp layout, so it never collides with an input.
SYNC_CHANNEL = 64
PICOHARP, HYDRAHARP = "picoharp", "hydraharp"
#: record classes, the order of the kernels' counters
_PHOTON, _MARKER, _SYNC, _OVERFLOW, _INVALID = range(5)


def default_engine() -> str:
    """numba where it is installed, else numpy."""
    return "numba" if HAVE_NUMBA else "numpy"


@dataclass(frozen=True)
class RecordFormat:
    """One TTTR record type (``TTResultFormat_TTTRRecType``) and how to decode it.

    Attributes
    ----------
    name : str
        PicoQuant's name without the ``rt`` prefix, e.g. ``"HydraHarp2T3"``.
    code : int
        The record type code, e.g. ``0x01010304``.
    mode : {"T2", "T3"}
    wrap : int
        Overflow period: syncs (T3) or timetag units (T2) per wrap.
    n_dtime_codes : int
        Codes of the dtime field (T3: 2**12 or 2**15), 0 in T2.
    layout : {"picoharp", "hydraharp"}
        The bit layout (see the module's docstring).
    multi_overflow : bool
        An overflow record carries its count of wraps (0 means one).
    n_channels : int
        Inputs the record can address (4 for the picoharp layout, 64 for hydraharp).
    """

    name: str
    code: int
    mode: str
    wrap: int
    n_dtime_codes: int
    layout: str
    multi_overflow: bool
    n_channels: int

    @property
    def is_t3(self) -> bool:
        return self.mode == "T3"


def _hh(name: str, code: int, mode: str, v1: bool = False) -> RecordFormat:
    if mode == "T3":
        return RecordFormat(name, code, "T3", 1024, 1 << 15, HYDRAHARP, not v1, 64)
    return RecordFormat(name, code, "T2", 33552000 if v1 else 1 << 25, 0, HYDRAHARP, not v1,
                        64)


#: Every record type of PicoQuant's published list. ``MultiHarp`` is also what
#: PicoHarp 330 writes (ptufile calls these two "Generic").
FORMATS: dict[int, RecordFormat] = {f.code: f for f in (
    RecordFormat("PicoHarpT3", 0x00010303, "T3", 65536, 1 << 12, PICOHARP, False, 4),
    RecordFormat("PicoHarpT2", 0x00010203, "T2", 210698240, 0, PICOHARP, False, 4),
    _hh("HydraHarpT3", 0x00010304, "T3", v1=True),
    _hh("HydraHarpT2", 0x00010204, "T2", v1=True),
    _hh("HydraHarp2T3", 0x01010304, "T3"),
    _hh("HydraHarp2T2", 0x01010204, "T2"),
    _hh("TimeHarp260NT3", 0x00010305, "T3"),
    _hh("TimeHarp260NT2", 0x00010205, "T2"),
    _hh("TimeHarp260PT3", 0x00010306, "T3"),
    _hh("TimeHarp260PT2", 0x00010206, "T2"),
    _hh("MultiHarpT3", 0x00010307, "T3"),
    _hh("MultiHarpT2", 0x00010207, "T2"),
)}


def record_format(code: int) -> RecordFormat:
    """The :class:`RecordFormat` of a record type code.

    Raises
    ------
    ValueError
        For a code PicoQuant does not publish, naming it in hex.

    Examples
    --------
    >>> record_format(0x01010304).name
    'HydraHarp2T3'
    >>> record_format(0x42)
    Traceback (most recent call last):
    ...
    ValueError: unknown PicoQuant record type 0x00000042; known: 0x00010203 (PicoHarpT2), ...
    """
    try:
        return FORMATS[int(code)]
    except KeyError:
        known = ", ".join(f"0x{c:08X} ({f.name})" for c, f in sorted(FORMATS.items()))
        raise ValueError(f"unknown PicoQuant record type 0x{int(code) & 0xFFFFFFFF:08X}; "
                         f"known: {known}") from None


@dataclass(frozen=True)
class Decoded:
    """The events of a run of records (see the module's docstring for their meaning).

    ``time`` is int64 timetags (T2) or uint64 sync numbers (T3); ``dtime`` is None in T2.
    ``wraps`` is the overflow count after the last record: pass it to the next chunk.
    """

    kind: np.ndarray
    channel: np.ndarray
    time: np.ndarray
    dtime: np.ndarray | None
    wraps: int
    n_photons: int
    n_markers: int
    n_sync: int
    n_overflow_records: int
    n_invalid: int

    @property
    def n_records(self) -> int:
        """Records decoded: every one is in exactly one counter."""
        return (self.n_photons + self.n_markers + self.n_sync + self.n_overflow_records
                + self.n_invalid)

    def __len__(self) -> int:
        return self.kind.size


@dataclass(frozen=True)
class Tally:
    """What :func:`histogram_records` saw.

    ``n_out_of_range`` photons (channel >= n_channels or dtime >= n_bins) are counted in
    ``n_photons`` but not in the histogram, so ``counts.sum()`` grows by
    ``n_photons - n_out_of_range``. ``max_dtime`` is over every photon, -1 when none.
    """

    n_photons: int = 0
    n_markers: int = 0
    n_overflow_records: int = 0
    n_invalid: int = 0
    n_out_of_range: int = 0
    wraps: int = 0
    max_dtime: int = -1

    @property
    def n_records(self) -> int:
        return self.n_photons + self.n_markers + self.n_overflow_records + self.n_invalid

    def then(self, later: Tally) -> Tally:
        """This tally followed by ``later`` (the tally of the next chunk of the stream)."""
        return Tally(self.n_photons + later.n_photons, self.n_markers + later.n_markers,
                     self.n_overflow_records + later.n_overflow_records,
                     self.n_invalid + later.n_invalid,
                     self.n_out_of_range + later.n_out_of_range, later.wraps,
                     max(self.max_dtime, later.max_dtime))


# --- numpy engine -----------------------------------------------------------------------

def _classify_numpy(words: np.ndarray, fmt: RecordFormat):
    """(class, channel, field, dtime, wraps added) of every record, as int64 arrays."""
    w = words.astype(np.int64)
    zero = np.zeros_like(w)
    cls = np.full(w.size, _INVALID, np.int64)
    if fmt.layout == PICOHARP:
        c = w >> 28
        special = c == 15
        if fmt.is_t3:
            field, dtime = w & 0xFFFF, (w >> 16) & 0xFFF
            bits = dtime
            photon = (c >= 1) & (c <= 4)
            sync = np.zeros(w.size, bool)
        else:
            field, dtime = w & 0x0FFFFFFF, zero
            bits = w & 0xF
            photon = (c >= 1) & (c <= 4)
            sync = c == 0
        overflow = special & (bits == 0)
        marker = special & (bits >= 1) & (bits <= 15)
        channel = np.where(special, bits, np.where(sync, SYNC_CHANNEL, c - 1))
        inc = overflow.astype(np.int64)
    else:
        c = (w >> 25) & 0x3F
        special = (w >> 31) == 1
        if fmt.is_t3:
            field, dtime = w & 0x3FF, (w >> 10) & 0x7FFF
            sync = np.zeros(w.size, bool)
        else:
            field, dtime = w & 0x1FFFFFF, zero
            sync = special & (c == 0)
        photon = ~special
        overflow = special & (c == 63)
        marker = special & (c >= 1) & (c <= 15)
        channel = np.where(sync, SYNC_CHANNEL, c)
        inc = np.where(overflow, np.maximum(field, 1) if fmt.multi_overflow else 1, 0)
    cls[photon] = _PHOTON
    cls[marker] = _MARKER
    cls[sync] = _SYNC
    cls[overflow] = _OVERFLOW
    return cls, channel, field, np.where(photon, dtime, 0), inc


#: Records per numpy step: the dozen int64 temporaries of a step stay in L2 (on the whole
#: 4 Mi-record chunk they page-fault and run from memory, ~4x slower).
NUMPY_STEP = 1 << 15


def _decode_numpy(words, fmt, wraps):
    parts, counts = [], np.zeros(5, np.int64)
    for start in range(0, words.size, NUMPY_STEP):
        cls, channel, field, dtime, inc = _classify_numpy(words[start:start + NUMPY_STEP],
                                                           fmt)
        before = wraps + np.cumsum(inc) - inc  # wraps in force at each record
        keep = (cls == _PHOTON) | (cls == _MARKER) | (cls == _SYNC)
        parts.append((np.where(cls[keep] == _MARKER, MARKER, PHOTON).astype(np.uint8),
                      channel[keep].astype(np.uint8), before[keep] * fmt.wrap + field[keep],
                      dtime[keep].astype(np.uint16)))
        counts += np.bincount(cls, minlength=5)
        wraps += int(inc.sum())
    if not parts:
        parts = [(np.zeros(0, np.uint8), np.zeros(0, np.uint8), np.zeros(0, np.int64),
                  np.zeros(0, np.uint16))]
    kind, channel, time, dtime = (np.concatenate(a) for a in zip(*parts, strict=True))
    return kind, channel, time, dtime, counts, wraps


def _histogram_numpy(words, fmt, counts, wraps):
    n_channels, n_bins = counts.shape
    n = np.zeros(5, np.int64)
    flat = counts.reshape(-1)  # a view: counts is C-contiguous
    n_out, max_dtime = 0, -1
    for start in range(0, words.size, NUMPY_STEP):
        cls, channel, _, dtime, inc = _classify_numpy(words[start:start + NUMPY_STEP], fmt)
        photon = cls == _PHOTON
        ch, dt = channel[photon], dtime[photon]
        ok = (ch < n_channels) & (dt < n_bins)
        # np.add.at: no temporary the size of the histogram (up to 16 MiB x 2 per call)
        np.add.at(flat, ch[ok] * n_bins + dt[ok], np.uint64(1))
        n += np.bincount(cls, minlength=5)
        n_out += int(ch.size - ok.sum())
        max_dtime = max(max_dtime, int(dt.max()) if dt.size else -1)
        wraps += int(inc.sum())
    return Tally(int(n[_PHOTON]), int(n[_MARKER]), int(n[_OVERFLOW]), int(n[_INVALID]),
                 n_out, wraps, max_dtime)


# --- numba engine: one loop per layout and mode ------------------------------------------
#
# The loops are plain functions here, compiled by numba in one of two ways (as the chip's
# loops are, stages.datapath): as C kernels loaded without numba (``_native``,
# stages.nativecode: a millisecond against numba's 0.5-2.5 s of import, typing and cache
# loading at a process's first call, most of `tcspc histogram`'s wall time on a small
# file), or through numba's dispatcher where that cannot be had (``_jitted``). A C kernel
# returns nothing, so the counters come back in ``counts`` / ``tally``; one signature per
# kind of loop (the picoharp loops take ``multi`` and ignore it).
#
# Counters live in locals (registers) and are stored once at the end: an increment of an
# array element per record is a store the compiler cannot keep apart from the output's (or
# the histogram's) stores.

#: ``counts`` of a decode loop: the five classes, then records out (5) and wraps (6, in
#: and out); ``tally`` of a histogram loop: the classes, out of range (5), wraps (6, in and
#: out), the largest dtime (7)
_N_OUT, _WRAPS, _MAX_DTIME = 5, 6, 7


def _decode_picoharp_t3(words, wrap, multi, kind, channel, time, dtime, counts):
    n = 0
    wraps = counts[_WRAPS]
    base = wraps * wrap
    n_photon = n_marker = n_sync = n_overflow = n_invalid = 0
    for i in range(words.size):
        w = np.int64(words[i])
        c = w >> 28
        d = (w >> 16) & 0xFFF
        if c == 15:
            if d == 0:
                n_overflow += 1
                wraps += 1
                base += wrap
                continue
            if d > 15:
                n_invalid += 1
                continue
            n_marker += 1
            kind[n] = MARKER
            channel[n] = d
            dtime[n] = 0
        elif 1 <= c <= 4:
            n_photon += 1
            kind[n] = PHOTON
            channel[n] = c - 1
            dtime[n] = d
        else:
            n_invalid += 1
            continue
        time[n] = base + (w & 0xFFFF)
        n += 1
    counts[_PHOTON] += n_photon
    counts[_MARKER] += n_marker
    counts[_SYNC] += n_sync
    counts[_OVERFLOW] += n_overflow
    counts[_INVALID] += n_invalid
    counts[_N_OUT] = n
    counts[_WRAPS] = wraps


def _decode_picoharp_t2(words, wrap, multi, kind, channel, time, dtime, counts):
    n = 0
    wraps = counts[_WRAPS]
    base = wraps * wrap
    n_photon = n_marker = n_sync = n_overflow = n_invalid = 0
    for i in range(words.size):
        w = np.int64(words[i])
        c = w >> 28
        if c == 15:
            m = w & 0xF
            if m == 0:
                n_overflow += 1
                wraps += 1
                base += wrap
                continue
            n_marker += 1
            kind[n] = MARKER
            channel[n] = m
        elif c == 0:
            n_sync += 1
            kind[n] = PHOTON
            channel[n] = SYNC_CHANNEL
        elif c <= 4:
            n_photon += 1
            kind[n] = PHOTON
            channel[n] = c - 1
        else:
            n_invalid += 1
            continue
        time[n] = base + (w & 0x0FFFFFFF)
        n += 1
    counts[_PHOTON] += n_photon
    counts[_MARKER] += n_marker
    counts[_SYNC] += n_sync
    counts[_OVERFLOW] += n_overflow
    counts[_INVALID] += n_invalid
    counts[_N_OUT] = n
    counts[_WRAPS] = wraps


def _decode_hydraharp_t3(words, wrap, multi, kind, channel, time, dtime, counts):
    n = 0
    wraps = counts[_WRAPS]
    base = wraps * wrap
    n_photon = n_marker = n_sync = n_overflow = n_invalid = 0
    for i in range(words.size):
        w = np.int64(words[i])
        c = (w >> 25) & 0x3F
        f = w & 0x3FF
        if w >> 31:
            if c == 63:
                k = max(f, 1) if multi else 1
                n_overflow += 1
                wraps += k
                base += k * wrap
                continue
            if c < 1 or c > 15:
                n_invalid += 1
                continue
            n_marker += 1
            kind[n] = MARKER
            dtime[n] = 0
        else:
            n_photon += 1
            kind[n] = PHOTON
            dtime[n] = (w >> 10) & 0x7FFF
        channel[n] = c
        time[n] = base + f
        n += 1
    counts[_PHOTON] += n_photon
    counts[_MARKER] += n_marker
    counts[_SYNC] += n_sync
    counts[_OVERFLOW] += n_overflow
    counts[_INVALID] += n_invalid
    counts[_N_OUT] = n
    counts[_WRAPS] = wraps


def _decode_hydraharp_t2(words, wrap, multi, kind, channel, time, dtime, counts):
    n = 0
    wraps = counts[_WRAPS]
    base = wraps * wrap
    n_photon = n_marker = n_sync = n_overflow = n_invalid = 0
    for i in range(words.size):
        w = np.int64(words[i])
        c = (w >> 25) & 0x3F
        f = w & 0x1FFFFFF
        if w >> 31:
            if c == 63:
                k = max(f, 1) if multi else 1
                n_overflow += 1
                wraps += k
                base += k * wrap
                continue
            if c == 0:
                n_sync += 1
                kind[n] = PHOTON
                channel[n] = SYNC_CHANNEL
            elif c <= 15:
                n_marker += 1
                kind[n] = MARKER
                channel[n] = c
            else:
                n_invalid += 1
                continue
        else:
            n_photon += 1
            kind[n] = PHOTON
            channel[n] = c
        time[n] = base + f
        n += 1
    counts[_PHOTON] += n_photon
    counts[_MARKER] += n_marker
    counts[_SYNC] += n_sync
    counts[_OVERFLOW] += n_overflow
    counts[_INVALID] += n_invalid
    counts[_N_OUT] = n
    counts[_WRAPS] = wraps


def _histogram_picoharp_t3(words, multi, hist, tally):
    n_channels, n_bins = hist.shape
    wraps = tally[_WRAPS]
    max_dtime = np.int64(-1)
    n_photon = n_marker = n_overflow = n_invalid = n_out = 0
    for i in range(words.size):
        w = np.int64(words[i])
        c = w >> 28
        d = (w >> 16) & 0xFFF
        if c == 15:
            if d == 0:
                n_overflow += 1
                wraps += 1
            elif d <= 15:
                n_marker += 1
            else:
                n_invalid += 1
        elif 1 <= c <= 4:
            n_photon += 1
            max_dtime = max(max_dtime, d)
            if c - 1 < n_channels and d < n_bins:
                hist[c - 1, d] += 1
            else:
                n_out += 1
        else:
            n_invalid += 1
    tally[_PHOTON] += n_photon
    tally[_MARKER] += n_marker
    tally[_OVERFLOW] += n_overflow
    tally[_INVALID] += n_invalid
    tally[_N_OUT] += n_out
    tally[_WRAPS] = wraps
    tally[_MAX_DTIME] = max_dtime


def _histogram_hydraharp_t3(words, multi, hist, tally):
    n_channels, n_bins = hist.shape
    wraps = tally[_WRAPS]
    max_dtime = np.int64(-1)
    n_photon = n_marker = n_overflow = n_invalid = n_out = 0
    for i in range(words.size):
        w = np.int64(words[i])
        c = (w >> 25) & 0x3F
        if w >> 31:
            if c == 63:
                n_overflow += 1
                wraps += max(w & 0x3FF, 1) if multi else 1
            elif 1 <= c <= 15:
                n_marker += 1
            else:
                n_invalid += 1
        else:
            d = (w >> 10) & 0x7FFF
            n_photon += 1
            max_dtime = max(max_dtime, d)
            if c < n_channels and d < n_bins:
                hist[c, d] += 1
            else:
                n_out += 1
    tally[_PHOTON] += n_photon
    tally[_MARKER] += n_marker
    tally[_OVERFLOW] += n_overflow
    tally[_INVALID] += n_invalid
    tally[_N_OUT] += n_out
    tally[_WRAPS] = wraps
    tally[_MAX_DTIME] = max_dtime


_LOOPS = {f.__name__[1:]: f for f in (
    _decode_picoharp_t3, _decode_picoharp_t2, _decode_hydraharp_t3, _decode_hydraharp_t2,
    _histogram_picoharp_t3, _histogram_hydraharp_t3)}
_P, _I = ctypes.c_void_p, ctypes.c_int64
#: decode: words, n, wrap, multi, kind, channel, time, dtime, n_dtime, counts;
#: histogram: words, n, multi, hist, n_channels, n_bins, tally
_ARGTYPES = {"decode": [_P, _I, _I, _I, _P, _P, _P, _P, _I, _P],
             "histogram": [_P, _I, _I, _P, _I, _I, _P]}
_JITTED: dict = {}


def _jitted(name: str):
    """The loop ``name`` through numba's dispatcher (and numba's on-disk cache)."""
    fn = _JITTED.get(name)
    if fn is None:
        import numba

        fn = _JITTED[name] = numba.njit(cache=True, nogil=True)(_LOOPS[name])
    return fn


def _native(name: str):
    """The loop ``name`` as a C kernel loaded without numba, or None (then ``_jitted``)."""
    from stages import nativecode

    kind = name.split("_")[0]
    return nativecode.kernel(name, __file__, _ARGTYPES[kind], lambda: _build(name, kind))


def _build(name: str, kind: str):
    import numba
    from numba import carray, types

    loop = numba.njit(nogil=True)(_LOOPS[name])
    p = types.CPointer
    u32, u64, i64, u8, u16 = types.uint32, types.uint64, types.int64, types.uint8, types.uint16
    if kind == "decode":
        sig = types.void(p(u32), i64, i64, i64, p(u8), p(u8), p(i64), p(u16), i64, p(i64))

        def c_decode(w, n, wrap, multi, kind_, channel, time, dtime, n_dtime, counts):
            loop(carray(w, (n,)), wrap, multi != 0, carray(kind_, (n,)),
                 carray(channel, (n,)), carray(time, (n,)), carray(dtime, (n_dtime,)),
                 carray(counts, (7,)))

        return numba.cfunc(sig, nopython=True)(c_decode)
    sig = types.void(p(u32), i64, i64, p(u64), i64, i64, p(i64))

    def c_histogram(w, n, multi, hist, n_channels, n_bins, tally):
        loop(carray(w, (n,)), multi != 0, carray(hist, (n_channels, n_bins)),
             carray(tally, (8,)))

    return numba.cfunc(sig, nopython=True)(c_histogram)


def _loop_name(fmt: RecordFormat, kind: str) -> str:
    return f"{kind}_{fmt.layout}_{fmt.mode.lower()}"


def _decode_numba(words, fmt, wraps):
    n = words.size
    kind, channel = np.empty(n, np.uint8), np.empty(n, np.uint8)
    time = np.empty(n, np.int64)
    dtime = np.empty(n if fmt.is_t3 else 0, np.uint16)
    counts = np.zeros(7, np.int64)
    counts[_WRAPS] = wraps
    name = _loop_name(fmt, "decode")
    fn = _native(name)
    if fn is not None:
        fn(words.ctypes.data, n, fmt.wrap, int(fmt.multi_overflow), kind.ctypes.data,
           channel.ctypes.data, time.ctypes.data, dtime.ctypes.data, dtime.size,
           counts.ctypes.data)
    else:
        _jitted(name)(words, np.int64(fmt.wrap), fmt.multi_overflow, kind, channel, time,
                      dtime, counts)
    m, wraps = int(counts[_N_OUT]), int(counts[_WRAPS])
    if m < n // 2:  # a sparse chunk: copy, so the caller does not hold buffers twice as big
        kind, channel, time, dtime = kind[:m].copy(), channel[:m].copy(), time[:m].copy(), \
            dtime[:m].copy()
    return kind[:m], channel[:m], time[:m], dtime[:m], counts[:5], wraps


def _histogram_numba(words, fmt, counts, wraps):
    tally = np.zeros(8, np.int64)
    tally[_WRAPS] = wraps
    name = _loop_name(fmt, "histogram")
    fn = _native(name)
    if fn is not None:
        fn(words.ctypes.data, words.size, int(fmt.multi_overflow), counts.ctypes.data,
           counts.shape[0], counts.shape[1], tally.ctypes.data)
    else:
        _jitted(name)(words, fmt.multi_overflow, counts, tally)
    return Tally(int(tally[_PHOTON]), int(tally[_MARKER]), int(tally[_OVERFLOW]),
                 int(tally[_INVALID]), int(tally[_N_OUT]), int(tally[_WRAPS]),
                 int(tally[_MAX_DTIME]))


def _check(words, engine):
    words = np.asarray(words)
    if words.dtype != np.uint32:
        raise TypeError(f"records must be uint32, found {words.dtype}")
    engine = engine or default_engine()
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {ENGINES}, found {engine!r}")
    if engine == "numba" and not HAVE_NUMBA:
        raise RuntimeError("engine='numba' requested but numba is not installed")
    return np.ascontiguousarray(words), engine


def decode_records(words: np.ndarray, fmt: RecordFormat, wraps: int = 0,
                   engine: str | None = None) -> Decoded:
    """Decode native uint32 records into events (photons, markers, T2 syncs).

    Parameters
    ----------
    words : ndarray of uint32
        Records in file order (native byte order: read the file as ``<u4``).
    fmt : RecordFormat
    wraps : int
        Overflow count before ``words[0]``: the ``wraps`` of the previous chunk's result.
    engine : {"numba", "numpy"}, optional
        Defaults to numba where it is installed.

    Examples
    --------
    >>> fmt = record_format(0x01010304)  # HydraHarp V2 T3
    >>> words = np.array([(1 << 25) | (100 << 10) | 7,   # photon, input 2, dtime 100
    ...                   (0x7F << 25) | 3,              # overflow: 3 wraps of 1024
    ...                   (1 << 31) | (2 << 25) | 5], np.uint32)  # marker bits 2
    >>> d = decode_records(words, fmt)
    >>> d.kind.tolist(), d.channel.tolist(), d.time.tolist(), d.dtime.tolist(), d.wraps
    ([0, 1], [1, 2], [7, 3077], [100, 0], 3)
    """
    words, engine = _check(words, engine)
    if engine == "numba":
        kind, channel, time, dtime, counts, wraps = _decode_numba(words, fmt, wraps)
    else:
        kind, channel, time, dtime, counts, wraps = _decode_numpy(words, fmt, int(wraps))
    return Decoded(kind, channel, time.view(np.uint64) if fmt.is_t3 else time,
                   dtime if fmt.is_t3 else None, int(wraps), int(counts[_PHOTON]),
                   int(counts[_MARKER]), int(counts[_SYNC]), int(counts[_OVERFLOW]),
                   int(counts[_INVALID]))


def histogram_records(words: np.ndarray, fmt: RecordFormat, counts: np.ndarray,
                      wraps: int = 0, engine: str | None = None) -> Tally:
    """Add the T3 photons of ``words`` into ``counts[channel, dtime]`` in place.

    No event arrays are built: this is the fast path of a micro-time histogram.

    Parameters
    ----------
    words : ndarray of uint32
    fmt : RecordFormat
        A T3 format.
    counts : ndarray of uint64, shape (n_channels, n_bins)
        Photons at a channel >= n_channels or a dtime >= n_bins are counted in
        ``n_out_of_range`` instead.
    wraps : int
        Overflow count before ``words[0]``; the result's ``wraps`` is the count after.

    Examples
    --------
    >>> fmt = record_format(0x00010303)  # PicoHarp T3
    >>> words = np.array([(1 << 28) | (5 << 16) | 9, (15 << 28), (2 << 28) | (4000 << 16)],
    ...                  np.uint32)
    >>> h = np.zeros((4, 16), np.uint64)
    >>> t = histogram_records(words, fmt, h)
    >>> int(h[0, 5]), t.n_photons, t.n_overflow_records, t.n_out_of_range, t.max_dtime
    (1, 2, 1, 1, 4000)
    """
    if not fmt.is_t3:
        raise ValueError(f"{fmt.name} is a T2 format: there is no dtime to histogram")
    if counts.dtype != np.uint64 or counts.ndim != 2:
        raise TypeError(f"counts must be a 2-d uint64 array, found {counts.ndim}-d "
                        f"{counts.dtype}")
    if not counts.flags.c_contiguous:
        raise ValueError("counts must be C-contiguous (it is updated in place)")
    words, engine = _check(words, engine)
    if engine == "numpy":
        return _histogram_numpy(words, fmt, counts, int(wraps))
    return _histogram_numba(words, fmt, counts, int(wraps))


def resolution_ps_fraction(resolution_s: float) -> Fraction:
    """A file's resolution in ps as an exact fraction (4e-12 s -> 4, 6.4e-11 -> 64).

    Headers store the resolution as a float (sometimes a float32 rounding of it:
    6.399999974426862e-11 for 64 ps); the nearest fraction with a denominator up to 1000
    within 1 ppm of it is the resolution meant.
    """
    if not resolution_s > 0:
        raise ValueError(f"resolution must be positive, found {resolution_s!r} s")
    ps = resolution_s * 1e12
    frac = Fraction(ps).limit_denominator(1000)
    if frac == 0 or abs(float(frac) - ps) > 1e-6 * ps:
        raise ValueError(f"resolution {resolution_s!r} s is not a fraction of a "
                         "picosecond with a denominator up to 1000")
    return frac


def to_picoseconds(timetags: np.ndarray, resolution_s: float) -> np.ndarray:
    """T2 timetags (int64, resolution units) to int64 ps, exactly (rounded half up).

    Examples
    --------
    >>> to_picoseconds(np.array([0, 3, 210698240]), 4.000000000000001e-12).tolist()
    [0, 12, 842792960]
    """
    frac = resolution_ps_fraction(resolution_s)
    t = np.asarray(timetags, np.int64)
    if frac.denominator == 1:
        return t * np.int64(frac.numerator)
    return (t * np.int64(frac.numerator) + frac.denominator // 2) // frac.denominator
