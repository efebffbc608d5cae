"""The source's raw-words messages made with one copy of the words.

:func:`pipeline.stream.wire.encode` of a raw-words batch writes an Arrow IPC stream: the
schema, the batch's metadata, then the words. For a given number of words everything
but the words is the same bytes, so :class:`RawWordsEncoder` keeps that message once per
batch size (made by ``wire.encode`` itself, so the two cannot drift) and fills a fresh
buffer with its head and tail and the words. The words are copied straight from where
they are, in either byte order and strided: a capture's big-endian words (which the
journal takes as they are) are byte-swapped into the message, and a worker's TDC range is
cut out of the batch by the same copy. Before, the source swapped a capture's words in
place, copied them back to big-endian for the journal, cut each worker's range into a
new array and copied it into the IPC stream: four passes over the words where this makes
one (docs/performance.md).
"""

from __future__ import annotations

import numpy as np

from pipeline.stream import wire

_MAX_SIZES = 8  #: templates kept (a source's batches come in one or two sizes)


class RawWordsEncoder:
    def __init__(self):
        self._templates: dict[int, tuple[bytes, int]] = {}

    def _template(self, n: int) -> tuple[bytes, int]:
        got = self._templates.get(n)
        if got is None:
            import pyarrow as pa

            from schemas.words import RAW_WORDS

            # words unlike any metadata, found from the end (the body is the last buffer)
            probe = ((np.arange(n, dtype=np.uint64) * 2654435761 + 0x9E3779B9)
                     & 0xFFFFFFFF).astype("<u4")
            ipc = wire.encode({}, pa.record_batch([pa.array(probe)],
                                                  schema=RAW_WORDS.schema))[1].to_pybytes()
            at = ipc.rfind(probe.tobytes())
            if at < 0:
                raise RuntimeError(f"raw-words IPC template of {n} words: body not found")
            if len(self._templates) >= _MAX_SIZES:
                self._templates.pop(next(iter(self._templates)))
            got = self._templates[n] = (ipc, at)
        return got

    def frames(self, header: dict, words: np.ndarray, token: str | None = None) -> list:
        """The frames ``wire.encode(header, <raw_words batch of words>, token)`` gives,
        bytes for bytes; ``words``: uint32 of either byte order, 1-D or a 2-D (cycles,
        TDCs) view, in row order."""
        head = wire.encode(header, None, token)[0]
        n = words.size
        ipc, at = self._template(n)
        out = np.empty(len(ipc), np.uint8)
        raw = memoryview(ipc)
        out[:at] = np.frombuffer(raw[:at], np.uint8)
        end = at + 4 * n
        out[end:] = np.frombuffer(raw[end:], np.uint8)
        dst = out[at:end].view("<u4")
        np.copyto(dst.reshape(words.shape), words, casting="unsafe")  # (the one copy)
        return [head, out]


def sparse_frames(header: dict, sparse, token: str | None = None) -> list:
    """The frames of a ``raw_sparse`` message (docs/streaming.md "Sparse raw words") of
    ``sparse`` (:class:`stages.datapath.SparseWords`): ``header`` as for ``raw_words``; its
    schema, version and ``n_words`` are set here."""
    import pyarrow as pa

    from schemas.words import RAW_SPARSE

    head = {**header, "schema": RAW_SPARSE.name, "version": RAW_SPARSE.version,
            "n_words": int(sparse.n)}
    return wire.encode(head, pa.record_batch([pa.array(sparse.index), pa.array(sparse.words)],
                                             schema=RAW_SPARSE.schema), token)


def sparse_parts(words: np.ndarray, first: int, n_tdc: int,
                 split: list[tuple[int, int]] | None):
    """``(whole, parts)``: the sparse form of a batch of whole cycles (the journal's frame
    is made from it) and each TDC range's, cut from it (one pass over the words)."""
    from stages.datapath import sparse_encode

    (whole,) = sparse_encode(words, first, n_tdc)
    parts = ([whole] if not split or list(split) == [(0, n_tdc)] else
             whole.cut(first, n_tdc, split))
    return whole, parts
