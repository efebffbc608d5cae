"""PicoQuant record decoders against a reference written here, record by record, from
PicoQuant's published description (doc/apx_tttrrecords.html and Read_PTU.py of
PicoQuant/PicoQuant-Time-Tagged-File-Format-Demos), and against an encoder written here."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stages.instruments.ptu import (
    FORMATS,
    SYNC_CHANNEL,
    Tally,
    decode_records,
    histogram_records,
    record_format,
    resolution_ps_fraction,
    to_picoseconds,
)

PICOHARP_T3, PICOHARP_T2 = 0x00010303, 0x00010203
HH1_T3, HH1_T2 = 0x00010304, 0x00010204
#: PicoQuant's list: code -> (mode, overflow period, dtime bits)
PUBLISHED = {
    0x00010303: ("T3", 65536, 12), 0x00010203: ("T2", 210698240, 0),
    0x00010304: ("T3", 1024, 15), 0x00010204: ("T2", 33552000, 0),
    0x01010304: ("T3", 1024, 15), 0x01010204: ("T2", 33554432, 0),
    0x00010305: ("T3", 1024, 15), 0x00010205: ("T2", 33554432, 0),
    0x00010306: ("T3", 1024, 15), 0x00010206: ("T2", 33554432, 0),
    0x00010307: ("T3", 1024, 15), 0x00010207: ("T2", 33554432, 0),
}
ALL_CODES = sorted(PUBLISHED)
T3_CODES = [c for c in ALL_CODES if PUBLISHED[c][0] == "T3"]


def reference_decode(words, code):
    """One record at a time, as PicoQuant describes it.

    Returns (events as (kind, channel, time, dtime) tuples, counters, wraps) where time
    is the overflow-corrected nsync (T3) or timetag (T2).
    """
    mode, period, _ = PUBLISHED[code]
    picoharp = code in (PICOHARP_T3, PICOHARP_T2)
    v1 = code in (HH1_T3, HH1_T2)
    events, ofl, wraps = [], 0, 0
    n = dict(photon=0, marker=0, sync=0, overflow=0, invalid=0)
    for w in words.tolist():
        if picoharp and mode == "T3":
            chan, dtime, nsync = w >> 28, (w >> 16) & 0xFFF, w & 0xFFFF
            if chan == 15:
                if dtime == 0:  # overflow
                    ofl, wraps = ofl + period, wraps + 1
                    n["overflow"] += 1
                elif dtime <= 15:  # marker bits (a PicoHarp has 4 marker inputs)
                    events.append((1, dtime, ofl + nsync, 0))
                    n["marker"] += 1
                else:
                    n["invalid"] += 1
            elif 1 <= chan <= 4:  # router channel 1..4 = input 1..4
                events.append((0, chan - 1, ofl + nsync, dtime))
                n["photon"] += 1
            else:  # "should not occur"
                n["invalid"] += 1
        elif picoharp:
            chan, timetag = w >> 28, w & 0x0FFFFFFF
            if chan == 15:
                markers = w & 0xF
                if markers == 0:
                    ofl, wraps = ofl + period, wraps + 1
                    n["overflow"] += 1
                else:
                    events.append((1, markers, ofl + timetag, 0))
                    n["marker"] += 1
            elif chan == 0:  # the sync input
                events.append((0, SYNC_CHANNEL, ofl + timetag, 0))
                n["sync"] += 1
            elif chan <= 4:
                events.append((0, chan - 1, ofl + timetag, 0))
                n["photon"] += 1
            else:
                n["invalid"] += 1
        else:
            special, chan = w >> 31, (w >> 25) & 0x3F
            if mode == "T3":
                dtime, t = (w >> 10) & 0x7FFF, w & 0x3FF
            else:
                dtime, t = 0, w & 0x1FFFFFF
            if special:
                if chan == 0x3F:
                    k = 1 if (v1 or t == 0) else t
                    ofl, wraps = ofl + period * k, wraps + k
                    n["overflow"] += 1
                elif 1 <= chan <= 15:
                    events.append((1, chan, ofl + t, 0))
                    n["marker"] += 1
                elif chan == 0 and mode == "T2":
                    events.append((0, SYNC_CHANNEL, ofl + t, 0))
                    n["sync"] += 1
                else:
                    n["invalid"] += 1
            else:
                events.append((0, chan, ofl + t, dtime))
                n["photon"] += 1
    return events, n, wraps


def as_events(d):
    dtime = d.dtime if d.dtime is not None else np.zeros(len(d), np.uint16)
    return list(zip(d.kind.tolist(), d.channel.tolist(), d.time.tolist(), dtime.tolist(),
                    strict=True))


def random_words(code, n, rng):
    """Random records, with every class well represented (raw random bits mostly give
    photons)."""
    words = rng.integers(0, 1 << 32, n, dtype=np.uint64).astype(np.uint32)
    pick = rng.random(n)
    if code in (PICOHARP_T3, PICOHARP_T2):
        words[pick < 0.3] |= np.uint32(0xF << 28)  # special
        ovf = pick < 0.1
        words[ovf] &= np.uint32(0xF000FFFF if code == PICOHARP_T3 else 0xFFFFFFF0)
        few = (pick >= 0.1) & (pick < 0.2)  # markers 1..15
        if code == PICOHARP_T3:
            words[few] = (words[few] & np.uint32(0xF000FFFF)) | (
                rng.integers(1, 16, few.sum()).astype(np.uint32) << 16)
    else:
        sp = pick < 0.4
        words[sp] |= np.uint32(1 << 31)
        ovf = pick < 0.15
        words[ovf] |= np.uint32(0x3F << 25)
        small = (pick >= 0.15) & (pick < 0.3)  # markers, and sync in T2
        words[small] = (words[small] & np.uint32(0x81FFFFFF)) | (
            rng.integers(0, 16, small.sum()).astype(np.uint32) << 25)
        low = ovf & (rng.random(n) < 0.3)  # overflow counts 0 and 1
        words[low] &= np.uint32(0xFFFFFC00 if PUBLISHED[code][0] == "T3" else 0xFE000000)
        words[low] |= rng.integers(0, 2, low.sum()).astype(np.uint32)
    return words


@pytest.mark.parametrize("code", ALL_CODES, ids=hex)
def test_formats_follow_the_published_table(code):
    fmt = record_format(code)
    mode, period, dtime_bits = PUBLISHED[code]
    assert (fmt.code, fmt.mode, fmt.wrap) == (code, mode, period)
    assert fmt.n_dtime_codes == (1 << dtime_bits if dtime_bits else 0)
    assert fmt.multi_overflow == (code not in (PICOHARP_T3, PICOHARP_T2, HH1_T3, HH1_T2))
    assert set(FORMATS) == set(PUBLISHED)


def test_unknown_record_type_names_the_code_in_hex():
    with pytest.raises(ValueError, match=r"unknown PicoQuant record type 0x00ABCDEF; known: "
                                         r"0x00010203 \(PicoHarpT2\)"):
        record_format(0xABCDEF)


@pytest.mark.parametrize("code", ALL_CODES, ids=hex)
def test_every_record_type_matches_the_reference(code, engine):
    rng = np.random.default_rng(code)
    words = random_words(code, 20000, rng)
    fmt = record_format(code)
    want, n, wraps = reference_decode(words, code)
    got = decode_records(words, fmt, engine=engine)
    assert as_events(got) == want
    assert (got.n_photons, got.n_markers, got.n_sync, got.n_overflow_records,
            got.n_invalid) == (n["photon"], n["marker"], n["sync"], n["overflow"], n["invalid"])
    assert got.n_records == words.size and got.wraps == wraps
    present = {k for k, v in n.items() if v}  # the random words exercise every class
    assert present == {"photon", "marker", "overflow", "invalid"} | (
        set() if fmt.is_t3 else {"sync"})
    assert got.time.dtype == (np.uint64 if fmt.is_t3 else np.int64)
    assert got.kind.dtype == got.channel.dtype == np.uint8
    assert got.dtime is None if not fmt.is_t3 else got.dtime.dtype == np.uint16


@pytest.mark.parametrize("code", ALL_CODES, ids=hex)
def test_engines_agree_on_every_record_type(code):
    words = random_words(code, 50000, np.random.default_rng(1))
    fmt = record_format(code)
    a = decode_records(words, fmt, wraps=7, engine="numba")
    b = decode_records(words, fmt, wraps=7, engine="numpy")
    for name in ("kind", "channel", "time", "dtime"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None and y is None) or (x.dtype == y.dtype and np.array_equal(x, y))
    assert (a.wraps, a.n_photons, a.n_markers, a.n_sync, a.n_overflow_records, a.n_invalid) \
        == (b.wraps, b.n_photons, b.n_markers, b.n_sync, b.n_overflow_records, b.n_invalid)
    if fmt.is_t3:
        ha, hb = (np.zeros((fmt.n_channels, 1000), np.uint64) for _ in range(2))
        ta = histogram_records(words, fmt, ha, 7, engine="numba")
        tb = histogram_records(words, fmt, hb, 7, engine="numpy")
        assert ta == tb and np.array_equal(ha, hb)


@pytest.mark.parametrize("code", ALL_CODES, ids=hex)
def test_the_loops_load_natively_and_every_way_agrees(code, monkeypatch):
    """The numba engine's loops run as C kernels loaded without numba (stages.nativecode),
    through numba's dispatcher (the fallback) and as plain Python: the numpy engine's
    events, counts and histograms each way."""
    import stages.instruments.ptu as ptu
    from stages import nativecode

    fmt = record_format(code)
    words = random_words(code, 3000, np.random.default_rng(code))
    name = ptu._loop_name(fmt, "decode")
    assert ptu._native(name) is not None, nativecode.failures.get(name)

    def once(engine):
        d = decode_records(words, fmt, wraps=3, engine=engine)
        out = [d.kind, d.channel, d.time, d.dtime, d.wraps, d.n_records, d.n_invalid]
        if fmt.is_t3:
            h = np.zeros((fmt.n_channels, 2000), np.uint64)
            out += [histogram_records(words, fmt, h, 3, engine), h]
        return out

    twin = once("numpy")
    native = once("numba")
    monkeypatch.setattr(ptu, "_native", lambda name: None)
    dispatched = once("numba")
    monkeypatch.setattr(ptu, "_jitted", lambda name: ptu._LOOPS[name])
    plain = once("numba")
    for got in (native, dispatched, plain):
        for a, b in zip(got, twin, strict=True):
            assert np.array_equal(a, b) if isinstance(a, np.ndarray) else a == b


def test_a_process_with_the_ptu_kernels_cached_runs_them_without_numba():
    """What `tcspc histogram` on a PTU file gains at start-up: once built, the C kernels
    load without importing numba or scipy."""
    import subprocess
    import sys

    import stages.instruments.ptu as ptu

    fmt = record_format(0x01010304)
    assert ptu._native(ptu._loop_name(fmt, "histogram")) is not None
    assert ptu._native(ptu._loop_name(fmt, "decode")) is not None
    code = ("import sys, numpy as np; from stages.instruments.ptu import *; "
            "f = record_format(0x01010304); w = np.arange(1000, dtype=np.uint32) << 10; "
            "h = np.zeros((64, 1 << 15), np.uint64); histogram_records(w, f, h); "
            "decode_records(w, f); "
            "print(sorted(m for m in ('numba', 'scipy') if m in sys.modules))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert res.stdout.strip() == "[]", res.stdout + res.stderr


# --- an encoder written here: events at known absolute times -> records ----------------------

def encode(code, times, channels, dtimes, rng):
    """Records for photons at absolute ``times`` (sorted), with the overflow records they
    need; multi-overflow formats pack up to the field's maximum per record and write a
    single wrap as 0 or 1 at random (both mean one)."""
    mode, period, _ = PUBLISHED[code]
    picoharp = code in (PICOHARP_T3, PICOHARP_T2)
    multi = not picoharp and code not in (HH1_T3, HH1_T2)
    max_count = 1023 if mode == "T3" else (1 << 25) - 1
    out, wraps = [], 0
    for t, c, d in zip(times.tolist(), channels.tolist(), dtimes.tolist(), strict=True):
        need = t // period - wraps
        while need > 0:
            k = min(need, max_count) if multi else 1
            if picoharp:
                out.append(0xF << 28)  # T3: dtime 0; T2: marker bits 0
            else:
                field = k if (k > 1 or rng.random() < 0.5) else 0
                out.append((1 << 31) | (0x3F << 25) | field)
            wraps, need = wraps + k, need - k
        f = t % period
        if picoharp and mode == "T3":
            out.append(((c + 1) << 28) | (d << 16) | f)
        elif picoharp:
            out.append(((c + 1) << 28) | f)
        elif mode == "T3":
            out.append((c << 25) | (d << 10) | f)
        else:
            out.append((c << 25) | f)
    return np.array(out, np.uint32), wraps


@pytest.mark.parametrize("code", ALL_CODES, ids=hex)
def test_many_wraps_give_exact_times(code, engine):
    """Times across many wraps come back exactly, also far past 2**53 (where a float would
    round): a multi-overflow record jumps there, and any format can start there."""
    rng = np.random.default_rng(code + 1)
    fmt = record_format(code)
    n = 3000
    gaps = rng.integers(0, 40 * fmt.wrap, n)  # up to 40 wraps between photons
    if fmt.multi_overflow:  # a few jumps of many wraps (T3: <= 4 Ki records each)
        jumps = rng.random(n) < 0.002
        jumps[n // 2] = True
        most = 1 << 12 if fmt.is_t3 else 1 << 20
        gaps[jumps] += rng.integers(1, most, jumps.sum()) * fmt.wrap * 1023
    times = np.cumsum(gaps).astype(np.int64)
    channels = rng.integers(0, fmt.n_channels, n)
    dtimes = rng.integers(0, max(fmt.n_dtime_codes, 1), n)
    words, wraps = encode(code, times, channels, dtimes, rng)
    got = decode_records(words, fmt, engine=engine)
    assert got.time.astype(np.int64).tolist() == times.tolist()
    assert got.channel.tolist() == channels.tolist()
    if fmt.is_t3:
        assert got.dtime.tolist() == dtimes.tolist()
    assert got.wraps == wraps and got.n_overflow_records == words.size - n
    if fmt.multi_overflow:
        assert int(times[-1]) > (1 << 32 if fmt.is_t3 else 1 << 53)
    start = (1 << 55) // fmt.wrap  # wraps before the chunk: times start near 2**55
    late = decode_records(words, fmt, wraps=start, engine=engine)
    assert late.time.astype(np.int64).tolist() == (times + start * fmt.wrap).tolist()
    assert late.wraps == start + wraps


@pytest.mark.parametrize("code", ALL_CODES, ids=hex)
@settings(max_examples=20, deadline=None)
@given(cuts=st.lists(st.integers(0, 6000), max_size=8), wraps0=st.integers(0, 1 << 30))
def test_chunked_decode_equals_whole(code, cuts, wraps0):
    words = random_words(code, 6000, np.random.default_rng(code))
    fmt = record_format(code)
    whole = decode_records(words, fmt, wraps0)
    bounds = [0, *sorted(cuts), words.size]
    parts, wraps = [], wraps0
    hist_whole = np.zeros((fmt.n_channels, 3000), np.uint64)
    hist_parts = np.zeros_like(hist_whole)
    tally = Tally(wraps=wraps0)
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        d = decode_records(words[a:b], fmt, wraps)
        parts.append(d)
        wraps = d.wraps
        if fmt.is_t3:
            tally = tally.then(histogram_records(words[a:b], fmt, hist_parts, tally.wraps))
    assert wraps == whole.wraps
    for name in ("kind", "channel", "time"):
        assert np.array_equal(np.concatenate([getattr(p, name) for p in parts]),
                              getattr(whole, name))
    assert sum(p.n_invalid for p in parts) == whole.n_invalid
    assert sum(p.n_records for p in parts) == words.size
    if fmt.is_t3:
        assert np.array_equal(np.concatenate([p.dtime for p in parts]), whole.dtime)
        t = histogram_records(words, fmt, hist_whole, wraps0)
        assert np.array_equal(hist_parts, hist_whole) and tally == t


@pytest.mark.parametrize("code", T3_CODES, ids=hex)
def test_histogram_is_the_decoded_photons_and_counts_the_rest(code, engine):
    words = random_words(code, 30000, np.random.default_rng(5))
    fmt = record_format(code)
    d = decode_records(words, fmt)
    photon = (d.kind == 0)
    n_channels, n_bins = 3, fmt.n_dtime_codes // 2
    hist = np.zeros((n_channels, n_bins), np.uint64)
    t = histogram_records(words, fmt, hist, engine=engine)
    ch, dt = d.channel[photon].astype(np.int64), d.dtime[photon].astype(np.int64)
    ok = (ch < n_channels) & (dt < n_bins)
    want = np.zeros_like(hist)
    np.add.at(want, (ch[ok], dt[ok]), 1)
    assert np.array_equal(hist, want)
    assert t.n_out_of_range == (~ok).sum() > 0
    assert int(hist.sum()) == t.n_photons - t.n_out_of_range
    assert t.n_records == words.size and t.wraps == d.wraps
    assert t.max_dtime == dt.max()
    assert (t.n_photons, t.n_markers, t.n_overflow_records, t.n_invalid) == (
        d.n_photons, d.n_markers, d.n_overflow_records, d.n_invalid)
    again = histogram_records(words, fmt, hist, engine=engine)  # adds, in place
    assert np.array_equal(hist, 2 * want) and again == t


def test_histogram_refuses_t2_and_bad_counts():
    words = np.zeros(4, np.uint32)
    with pytest.raises(ValueError, match="PicoHarpT2 is a T2 format"):
        histogram_records(words, record_format(PICOHARP_T2), np.zeros((4, 8), np.uint64))
    with pytest.raises(TypeError, match="counts must be a 2-d uint64 array"):
        histogram_records(words, record_format(PICOHARP_T3), np.zeros((4, 8), np.int64))
    with pytest.raises(TypeError, match="records must be uint32, found int64"):
        decode_records(words.astype(np.int64), record_format(PICOHARP_T3))


def test_empty_input(engine):
    for code in ALL_CODES:
        d = decode_records(np.zeros(0, np.uint32), record_format(code), 5, engine=engine)
        assert len(d) == 0 and d.n_records == 0 and d.wraps == 5


def test_picoseconds_are_exact():
    big = np.array([0, 1, (1 << 53) + 1, (1 << 60) // 64], np.int64)
    assert to_picoseconds(big, 4e-12).tolist() == (big * 4).tolist()
    assert to_picoseconds(big, 6.399999974426862e-11).tolist() == (big * 64).tolist()
    assert to_picoseconds(np.array([1, 2, 3]), 0.5e-12).tolist() == [1, 1, 2]  # half up
    assert resolution_ps_fraction(9.999999960041972e-13) == 1
    with pytest.raises(ValueError, match="must be positive"):
        resolution_ps_fraction(0.0)
