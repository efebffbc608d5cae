import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from schemas import ARTIFACT, HIT, INVALID_PHASE, MALFORMED, NO_HIT
from stages.codec import (
    JOHNSON,
    PHASE_DECODE,
    classify_words,
    decode_fields,
    encode_words,
)

fields = st.tuples(st.integers(0, 63), st.integers(0, 7), st.integers(0, 31),
                   st.integers(0, 7), st.integers(0, 255))


@given(st.lists(fields, min_size=1, max_size=200))
def test_decode_encode_roundtrip(rows):
    c1, p1, c2, p2, a = (np.array(col) for col in zip(*rows, strict=True))
    f = decode_fields(encode_words(c1, p1, c2, p2, a))
    assert np.array_equal(f.c1st, c1) and np.array_equal(f.p1st, p1)
    assert np.array_equal(f.c2nd, c2) and np.array_equal(f.p2nd, p2)
    assert np.array_equal(f.address, a) and f.markers_ok.all()
    assert np.array_equal(f.d1st, 8 * c1 + p1)  # eq. 3.2
    assert np.array_equal(f.d2nd, 8 * c2 + p2)  # eq. 3.3


@given(arrays(np.uint32, st.integers(1, 300)))
def test_encode_decode_roundtrip_of_any_wellformed_word(words):
    words = (words & ~np.uint32((1 << 31) | (7 << 9) | 1)) | np.uint32(1 << 9)
    f = decode_fields(words)
    again = encode_words(f.c1st, f.p1st_raw, f.c2nd, f.p2nd_raw, f.address, raw_phase=True)
    assert np.array_equal(again, words)


def test_all_sixteen_phase_codes():
    expected = {0b0000: 0, 0b0001: 1, 0b0011: 2, 0b0111: 3, 0b1111: 4, 0b1110: 5,
                0b1100: 6, 0b1000: 7}
    for code in range(16):
        assert PHASE_DECODE[code] == expected.get(code, -1), bin(code)
        w = encode_words(1, code, 1, 0, 0, raw_phase=True)
        cls = classify_words(w, 1)
        assert cls[0] == (HIT if code in expected else INVALID_PHASE)
        w2 = encode_words(1, 0, 1, code, 0, raw_phase=True)
        assert classify_words(w2, 1)[0] == (HIT if code in expected else INVALID_PHASE)
    assert list(JOHNSON) == list(expected)


def test_table_5_1_byte_layout():
    # Byte 1 first, bit 1 of each byte the MSB: C2nd=0b10101, P2nd=0b0111, C1st=0b110011,
    # P1st=0b1110, A=0b10010110.
    w = encode_words(0b110011, 0b1110, 0b10101, 0b0111, 0b10010110, raw_phase=True)
    b = int(w).to_bytes(4, "big")
    assert b[0] == 0b0_10101_01   # 0, C2nd4..0, P2nd3..2
    assert b[1] == 0b11_110011    # P2nd1..0, C1st5..0
    assert b[2] == 0b1110_0_0_1_1  # P1st3..0, 0, 0, 1, A7
    assert b[3] == 0b0010110_0    # A6..0, 0


def test_class_precedence():
    base = encode_words(3, 2, 5, 1, 0)
    bad_marker = base | np.uint32(1)
    bubble = encode_words(3, 0b0101, 5, 1, 0, raw_phase=True)
    zero = encode_words(0, 0, 0, 0, 0)
    art = encode_words(3, 2, 31, 7, 0)
    words = np.array([base, bad_marker, bubble | np.uint32(1 << 31), bubble, zero, art],
                     np.uint32)
    cls = classify_words(words, 1, n_min=[1], n_max=[100])
    assert cls.tolist() == [HIT, MALFORMED, MALFORMED, INVALID_PHASE, NO_HIT, ARTIFACT]
    # no_hit wins over artifact: D2nd = 0 is below n_min = 1
    assert classify_words(zero, 1, n_min=[1], n_max=[100])[0] == NO_HIT


def test_address_must_match_position():
    w = encode_words(1, 1, 1, 1, [0, 1, 2, 3, 1, 0])  # last two swapped
    assert classify_words(w, 3).tolist() == [HIT, HIT, HIT, MALFORMED, HIT, MALFORMED]
    # the first word's position comes from its stream index
    assert classify_words(w[1:], 3, first_word=1)[:2].tolist() == [HIT, HIT]
    assert (classify_words(encode_words(1, 1, 1, 1, 200), 128) == MALFORMED).all()


def test_encode_rejects_out_of_range_fields():
    with pytest.raises(ValueError, match=r"c1st must be in 0..63, found \[64\]"):
        encode_words(64, 0, 0, 0, 0)
    with pytest.raises(ValueError, match="p1st must be in 0..7"):
        encode_words(1, 8, 0, 0, 0)
