"""LinoSPAD2 words: pixel maps, accounting, chunking and the code-density calibration."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stages.instruments import linospad2 as lino

WPL = 6  # short lines keep the synthetic words small


def widths_table(rng, rows=lino.N_PIXEL, dead_lead=(15, 28), extra_dead=8):
    """(rows, 140) code widths summing to 2500 ps: a dead lead-in, a few dead codes inside,
    the rest lognormal (a carry chain's DNL is tens of %)."""
    w = rng.lognormal(0.0, 0.4, size=(rows, lino.N_FINE))
    lead = rng.integers(*dead_lead, size=rows)
    w[np.arange(lino.N_FINE)[None, :] < lead[:, None]] = 0.0
    for r in range(rows):
        w[r, rng.choice(np.arange(30, lino.N_FINE), extra_dead, replace=False)] = 0.0
    return w / w.sum(axis=1, keepdims=True) * lino.CLOCK_PS


def word(tdc_bits_code, valid=True):
    bits, code = tdc_bits_code
    return np.uint32((1 << 31 if valid else 0) | (bits << 28) | code)


# ------------------------------------------------------------------------ pixel maps

def test_2212b_and_2212s_map_the_same_words_to_different_pixels():
    words = np.zeros((1, lino.LINES, WPL), np.uint32)
    expected_b, expected_s = [], []
    for slot, (tdc, bits) in enumerate([(0, 0), (0, 3), (1, 2), (63, 1), (17, 3)]):
        words[0, tdc, slot] = word((bits, 1000 + slot))
        expected_b.append(4 * tdc + bits)
        expected_s.append(tdc + 64 * bits)
    order = np.lexsort((np.arange(5), [0, 0, 1, 63, 17]))  # file order: by TDC, then slot
    for fw, expected in (("2212b", expected_b), ("2212s", expected_s)):
        d = lino.decode_words(words.ravel(), fw, WPL)
        assert d.pixel.tolist() == np.array(expected)[order].tolist(), fw
        assert d.tdc.tolist() == [0, 0, 1, 17, 63]
        assert lino.tdc_of(d.pixel, fw).tolist() == d.tdc.tolist()
    # the histograms by pixel are the same counts under the two maps, permuted
    hb, _ = lino.fine_histograms(words.ravel(), "2212b", "pixel", WPL)
    hs, _ = lino.fine_histograms(words.ravel(), "2212s", "pixel", WPL)
    tdc, bits = np.divmod(np.arange(256), 4)
    np.testing.assert_array_equal(hb[4 * tdc + bits], hs[tdc + 64 * bits])


def test_pixel_maps_are_bijections():
    tdc, bits = np.meshgrid(np.arange(64), np.arange(4), indexing="ij")
    for fw in lino.FIRMWARES:
        pix = lino.pixel_of(tdc, bits, fw)
        assert sorted(pix.ravel().tolist()) == list(range(256))
        np.testing.assert_array_equal(lino.tdc_of(pix, fw), tdc)


def test_firmware_2208_and_unknown_are_refused_with_reasons():
    with pytest.raises(ValueError, match="256 lines"):
        lino.check_firmware("2208")
    with pytest.raises(ValueError, match="unknown LinoSPAD2 firmware"):
        lino.decode_words(np.zeros(lino.LINES * WPL, np.uint32), "2212x", WPL)


# ------------------------------------------------------------------------ accounting

@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 4), st.integers(1, 9))
def test_every_word_is_accounted_for(seed, cycles, wpl):
    """Any 32-bit words at all (garbage included): valid + invalid + line65 = words, and
    each count is what an independent count of the bits says."""
    rng = np.random.default_rng(seed)
    w = rng.integers(0, 2**32, size=cycles * lino.LINES * wpl, dtype=np.uint64).astype(np.uint32)
    d = lino.decode_words(w, "2212b", wpl)
    t = d.tally
    assert t.accounted and t.words == w.size and t.cycles == cycles
    grid = w.reshape(cycles, lino.LINES, wpl)
    assert t.valid == int((grid[:, :64] >= 2**31).sum()) == len(d)
    assert t.line65 == cycles * wpl
    assert t.line65_valid == int((grid[:, 64] >= 2**31).sum())
    counts, t2 = lino.fine_histograms(w, "2212s", "tdc", wpl)
    assert t2 == t and int(counts.sum()) == t.valid


def test_partial_cycles_and_wrong_types_are_refused():
    with pytest.raises(ValueError, match="whole number of cycles"):
        lino.decode_words(np.zeros(lino.LINES * WPL + 1, np.uint32), "2212b", WPL)
    with pytest.raises(ValueError, match="unsigned 32-bit"):
        lino.fine_histograms(np.zeros(lino.LINES * WPL), "2212b", "tdc", WPL)
    with pytest.raises(ValueError, match="by must be"):
        lino.fine_histograms(np.zeros(lino.LINES * WPL, np.uint32), "2212b", "row", WPL)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.integers(1, 7), min_size=1, max_size=6), st.sampled_from(lino.FIRMWARES),
       st.sampled_from(["tdc", "pixel"]))
def test_chunks_add_up_to_the_whole(sizes, firmware, by):
    """Histograms and tallies of any split into whole cycles add up to the whole's; the
    decoded chunks concatenate to the whole's decode."""
    rng = np.random.default_rng(sum(sizes))
    w = lino.simulate_words(widths_table(rng), sum(sizes), rng, firmware, WPL)
    whole_counts, whole_tally = lino.fine_histograms(w, firmware, by, WPL)
    whole = lino.decode_words(w, firmware, WPL)
    counts = np.zeros_like(whole_counts)
    tally = lino.Tally()
    parts = []
    starts = np.cumsum([0, *sizes])
    for i in range(len(sizes)):
        chunk = w[starts[i] * lino.LINES * WPL: starts[i + 1] * lino.LINES * WPL]
        c, t = lino.fine_histograms(chunk, firmware, by, WPL)
        counts += c
        tally = tally + t
        parts.append(lino.decode_words(chunk, firmware, WPL, first_cycle=int(starts[i])))
    np.testing.assert_array_equal(counts, whole_counts)
    assert tally == whole_tally
    for name, col in whole.columns().items():
        np.testing.assert_array_equal(np.concatenate([p.columns()[name] for p in parts]), col)


def test_simulated_words_decode_to_what_was_simulated():
    rng = np.random.default_rng(7)
    w = lino.simulate_words(widths_table(rng, rows=64), 3, rng, "2212b", WPL, fill=0.7)
    d = lino.decode_words(w, "2212b", WPL)
    grid = w.reshape(3, lino.LINES, WPL)
    assert np.array_equal(grid >> 31, (grid >> 30) & 1)   # bit 30 mirrors bit 31, as real
    assert d.fine.max() < lino.N_FINE and np.all(d.fine == d.code % 140)
    # codes increase along each line
    key = d.cycle.astype(np.int64) * 64 + d.tdc
    same = key[1:] == key[:-1]
    assert np.all(np.diff(d.code.astype(np.int64))[same] > 0)


# ---------------------------------------------------------------------- code density

def test_code_density_recovers_a_known_width_table_within_binomial_error():
    """Uniform light from a known (256, 140) width table, through real words: every code
    time within the binomial error, the normalised errors' RMS ~1, dead codes width 0."""
    rng = np.random.default_rng(2024)
    truth = widths_table(rng)
    w = lino.simulate_words(truth, 120, rng, "2212b", words_per_line=40, fill=0.6)
    counts, tally = lino.fine_histograms(w, "2212b", "pixel", 40)
    cd = lino.code_density(counts)
    assert tally.accounted and cd.hits.min() > 500
    true_upper = np.cumsum(truth, axis=1)
    f = np.clip(true_upper / lino.CLOCK_PS, 0.0, 1.0)
    sigma = np.sqrt(f * (1 - f) / cd.hits[:, None]) * lino.CLOCK_PS
    inside = (f > 0) & (f < 1)
    z = (cd.upper_ps - true_upper)[inside] / sigma[inside]
    assert 0.85 < np.sqrt(np.mean(z ** 2)) < 1.15
    assert np.abs(z).max() < 5.5   # ~27 000 codes: a 5.5-sigma excursion is ~1e-3 likely
    assert np.all(cd.width_ps[truth == 0] == 0) and np.all(cd.dead[truth == 0])
    np.testing.assert_allclose(cd.upper_ps[:, -1], lino.CLOCK_PS)
    np.testing.assert_allclose(cd.centre_ps, (cd.lower_ps + cd.upper_ps) / 2)
    assert np.all(np.diff(cd.upper_ps, axis=1) >= 0)   # monotonic INL table


def test_code_density_rejects_bad_counts_and_flags_empty_rows():
    with pytest.raises(ValueError, match=r"\(n, 140\)"):
        lino.code_density(np.zeros((4, 139), np.int64))
    with pytest.raises(ValueError, match="non-negative"):
        lino.code_density(-np.ones((1, 140), np.int64))
    cd = lino.code_density(np.zeros((2, 140), np.uint64))
    assert np.all(np.isnan(cd.width_ps)) and cd.hits.tolist() == [0, 0]
    with pytest.raises(ValueError, match="convention"):
        cd.code_time_ps("middle")


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 3))
def test_published_counts_are_recovered_from_the_cumulative_table(seed, multiple):
    rng = np.random.default_rng(seed)
    counts = rng.poisson(3.0, size=(8, lino.N_FINE)) * multiple
    counts[:, :20] = 0
    counts[3] = 0   # an empty row
    table = np.cumsum(counts, axis=1) / np.maximum(counts.sum(1), 1)[:, None] * lino.CLOCK_PS
    rec, n = lino.counts_from_cumulative(table)
    assert n[3] == 0 and np.all(rec[3] == -1)
    live = n > 0
    # the same table (the counts up to a common factor, which the table cannot tell)
    np.testing.assert_allclose(lino.code_density(rec[live]).upper_ps, table[live], atol=1e-9)
    factor = counts[live].sum(1) // n[live]      # 1, or a common factor of the counts
    np.testing.assert_array_equal(rec[live] * factor[:, None], counts[live])


def test_comparison_is_statistics_for_equal_chains_and_not_for_a_shift():
    """Two captures of the same chains disagree as binomial statistics says; a published
    table shifted by one code's half-width (a convention slip) stands out."""
    rng = np.random.default_rng(99)
    truth = widths_table(rng)
    n = rng.integers(300, 900, size=256)
    p = truth / lino.CLOCK_PS
    a = rng.multinomial(n, p)
    b = rng.multinomial(n, p)
    pub = lino.code_density(b).upper_ps
    c = lino.compare_code_times(a, pub, rng=np.random.default_rng(1), n_null=100)
    assert np.all(c.live) and np.array_equal(c.published_hits, n)
    np.testing.assert_array_equal(c.hits, n)
    ratio = c.ratio
    assert 0.7 < np.median(ratio) < 1.0          # pure statistics: ~0.84 (cumulative codes)
    assert np.mean(ratio < 2) > 0.93
    assert 0.3 < np.mean(c.p_value < 0.5) < 0.7   # p-values ~uniform
    assert np.all(c.max_ps >= c.rms_ps)
    # the dead codes of the truth are dead in both
    assert np.all(c.dead_in_both >= (truth == 0).sum(1))
    # the same data compared in the wrong convention: mean offset ~ -w/2 ~ -8 ps
    wrong = lino.compare_code_times(a, pub, "centre")
    assert np.mean(wrong.mean_ps) < np.mean(c.mean_ps) - 6
    shifted = lino.compare_code_times(a, np.clip(pub + 30.0, 0, 2500) * (pub > 0))
    assert np.median(shifted.rms_ps / shifted.expected_rms_ps) > 1.0
    with pytest.raises(ValueError, match="needs an rng"):
        lino.compare_code_times(a, pub, n_null=5)
    with pytest.raises(ValueError, match="does not match"):
        lino.compare_code_times(a[:10], pub)


@pytest.mark.parametrize("firmware", lino.FIRMWARES)
def test_pixels_of_one_chain_agree_and_of_different_chains_do_not(firmware):
    rng = np.random.default_rng(17)
    per_tdc = widths_table(rng, rows=64)
    n = np.full(256, 3000)
    shared = rng.multinomial(n, per_tdc[lino.tdc_of(np.arange(256), firmware)] / 2500)
    c = lino.pixels_against_their_tdc(shared, firmware, np.random.default_rng(0), 50)
    assert 0.7 < np.median(c.ratio) < 1.0 and np.mean(c.p_value < 0.01) < 0.05
    own = rng.multinomial(n, widths_table(rng) / 2500)      # every pixel its own chain
    c = lino.pixels_against_their_tdc(own, firmware)
    assert np.median(c.ratio) > 2
    assert lino.pool_by_tdc(shared, firmware).sum() == shared.sum()
