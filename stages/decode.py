"""The decode stage: raw words to a ``decoded_events`` Arrow batch, every word classified."""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from schemas.words import DECODED_EVENTS, NO_HIT, class_dictionary
from stages.artifact import ArtifactBounds
from stages.codec import classify_words, decode_fields, positions


def decode_batch(words: np.ndarray, n_tdc: int, first_word: int = 0,
                 bounds: ArtifactBounds | None = None,
                 include_no_hit: bool = False) -> tuple[pa.RecordBatch, np.ndarray]:
    """Decode and classify ``words``.

    Returns
    -------
    batch : pyarrow.RecordBatch
        ``decoded_events`` rows, one per word (no_hit words only when
        ``include_no_hit``: they carry no time, and are counted in the class counts).
    cls : ndarray of uint8
        The class code of every word of the input, kept rows or not.

    Examples
    --------
    >>> from stages.codec import encode_words
    >>> b, cls = decode_batch(encode_words([5, 0], [3, 0], [2, 0], [1, 0], [0, 1]), 2)
    >>> b.num_rows, b.column("d1st").to_pylist(), cls.tolist()
    (1, [43], [0, 1])
    """
    w = np.asarray(words, np.uint32)
    f = decode_fields(w)
    lo = bounds.n_min if bounds is not None else None
    hi = bounds.n_max if bounds is not None else None
    cls = classify_words(w, n_tdc, first_word, lo, hi, fields=f)
    keep = slice(None) if include_no_hit else cls != NO_HIT
    p1, p2 = f.p1st[keep], f.p2nd[keep]
    d1, d2 = f.d1st[keep], f.d2nd[keep]
    bad = f.markers_ok[keep] == 0
    cycle = (np.arange(w.size, dtype=np.uint64) + np.uint64(first_word)) // np.uint64(n_tdc)

    def masked(values, invalid, dtype):
        return pa.array(values.astype(dtype), mask=invalid | bad)

    batch = pa.RecordBatch.from_arrays([
        pa.array(cycle[keep]),
        pa.array(positions(w.size, n_tdc, first_word)[keep]),
        pa.array(w[keep]),
        pa.DictionaryArray.from_arrays(pa.array(cls[keep].astype(np.int8)),
                                       class_dictionary()),
        pa.array(f.c1st[keep]),
        masked(p1, p1 < 0, np.uint8),
        pa.array(f.c2nd[keep]),
        masked(p2, p2 < 0, np.uint8),
        masked(d1, d1 < 0, np.uint16),
        masked(d2, d2 < 0, np.uint16),
    ], schema=DECODED_EVENTS.schema)
    return batch, cls
