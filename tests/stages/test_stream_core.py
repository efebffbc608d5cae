"""The histogram core's measurements: fixed by word index, whatever the batching or gaps."""

import numpy as np
import pyarrow as pa
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas.words import RAW_WORDS
from stages.histogram import HistogramAccumulator, HistogramState
from stages.stream import HistogramCore
from stages.testpattern import pattern_words

N, M, CYCLES = 8, 50, 330
WORDS, _ = pattern_words(CYCLES, N, hit_prob=0.3, malformed_prob=0.02, rng=4)


def feed(core, pieces):
    out = []
    for first, w in pieces:
        batch = pa.record_batch([pa.array(w)], schema=RAW_WORDS.schema)
        out += core.process({"run": "r", "first_word": first, "seq": 0,
                             "t_laser_win_ns": 140.0}, batch)
    return out + core.finish({"run": "r"})


@settings(max_examples=40, deadline=None)
@given(cuts=st.lists(st.integers(1, WORDS.size - 1), max_size=8, unique=True),
       drop=st.sets(st.integers(0, 8), max_size=2))
def test_measurements_depend_on_word_index_only(cuts, drop):
    edges = [0, *sorted(cuts), WORDS.size]
    pairs = zip(edges[:-1], edges[1:], strict=True)
    pieces = [(a, WORDS[a:b]) for i, (a, b) in enumerate(pairs)
              if i not in drop]
    kept = np.zeros(WORDS.size, bool)
    for a, w in pieces:
        kept[a:a + w.size] = True
    got = {h["measurement_index"]: HistogramState.from_table(pa.Table.from_batches([b]))
           for h, b in feed(HistogramCore(N, measurement_cycles=M), pieces)}
    for k in range(-(-CYCLES // M)):
        sl = slice(k * M * N, (k + 1) * M * N)
        if not kept[sl].any():
            assert k not in got  # nothing arrived for it: nothing sent
            continue
        acc = HistogramAccumulator(N)
        idx = np.flatnonzero(kept[sl]) + sl.start
        for run in np.split(idx, np.flatnonzero(np.diff(idx) != 1) + 1):
            acc.update(WORDS[run[0]:run[-1] + 1], int(run[0]))
        ref = acc.snapshot()
        assert np.array_equal(got[k].hits, ref.hits), k
        assert np.array_equal(got[k].class_counts, ref.class_counts), k
    assert set(got) <= set(range(-(-CYCLES // M)))


def test_one_measurement_without_measurement_cycles():
    out = feed(HistogramCore(N), [(0, WORDS[:100]), (100, WORDS[100:])])
    assert len(out) == 1 and out[0][0]["measurement"] == "r"
    assert HistogramState.from_table(pa.Table.from_batches([out[0][1]])).words == WORDS.size
