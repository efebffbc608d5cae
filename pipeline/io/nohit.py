"""The journal's ``zstd-nohit`` frames: raw words with their no-hit pattern taken out.

A TDC that saw no photon in a cycle sends its no-hit word, a constant of its position
(docs/design.md "Raw word": ``0x200 | address << 1``, the address the position's low 8
bits), so most of a photon-starving stream is a pattern known in advance. A frame's
content (one zstd frame, level ``NOHIT_LEVEL``, with zstd's content checksum) is::

    header   20 bytes, little-endian: b"TJN1", n_tdc (u32), words (u32), first_word (u64)
    mask     ceil(words / 8) bytes: bit i (np.packbits, little bit order) set where word i
             differs from its position's no-hit word; position (first_word + i) % n_tdc
    others   the words whose bit is set, big-endian, in stream order

It is lossless for any words (malformed, invalid, a wrong address are simply "differs"),
self-describing (a frame decodes with nothing but its bytes, so a segment reads without its
index) and checked twice: zstd's checksum over the content, then the content's own sizes
(the mask's count of set bits is the number of words that follow, the header's count what
the index says). Encoding is one comparison against a cached tile of the pattern, a pack of
the booleans and a gather of the few words that differ (one pass of a compiled kernel,
stages.nativecode, or its numpy twin where none can be had): zstd then compresses ~8 % of
the bytes at 5 % hits and ~22 % at 18 %, not all of them.
"""

from __future__ import annotations

import struct

import numpy as np

from stages.datapath import no_hit_words  # the one definition of the pattern

MAGIC = b"TJN1"
HEADER = struct.Struct("<4sIIQ")  # magic, n_tdc, words, first_word


class FrameError(ValueError):
    """A frame's content that is not a well-formed ``zstd-nohit`` frame (the reason)."""


_tiles: dict[tuple[int, str], np.ndarray] = {}


def _tile(n_tdc: int, words: int, order: str) -> np.ndarray:
    """The no-hit pattern repeated over at least ``words + n_tdc`` words, as uint32 holding
    the bytes of words of dtype ``order`` (">u4" or "<u4"); cached and grown per n_tdc."""
    t = _tiles.get((n_tdc, order))
    if t is None or t.size < words + n_tdc:
        reps = -(-max(words, 1 << 18, t.size if t is not None else 0) // n_tdc) + 1
        t = np.tile(no_hit_words(n_tdc).astype(order), reps).view(np.uint32)
        _tiles[(n_tdc, order)] = t
    return t


def encode(words: np.ndarray, first_word: int, n_tdc: int, native: bool = True) -> bytes:
    """A frame's content (before zstd) for ``words`` (uint32, native or big-endian), the
    first of them at stream index ``first_word``. ``native=False``: numpy only (the
    compiled kernel's twin, which runs where no kernel can be had)."""
    if words.dtype not in (np.dtype(">u4"), np.dtype("<u4")) or not words.flags.c_contiguous:
        words = np.ascontiguousarray(words, dtype=">u4")
    order = words.dtype.str  # ">u4" or "<u4", whichever is native
    u = words.view(np.uint32)  # the bytes as they are, compared with the pattern's bytes
    n = u.size
    off = first_word % n_tdc
    pattern = _tile(n_tdc, n, order)[off:off + n]
    fn = _kernel() if native and n >= 8 else None
    if fn is not None:
        mask, others, fill = np.empty(-(-n // 8), np.uint8), np.empty(n, np.uint32), \
            np.zeros(1, np.int64)
        fn(u.ctypes.data, n, pattern.ctypes.data, mask.ctypes.data, others.ctypes.data,
           fill.ctypes.data)
        k, whole = int(fill[0]), n // 8 * 8
        if whole < n:  # the words of the last, part byte
            differs = u[whole:] != pattern[whole:]
            mask[-1] = np.packbits(differs, bitorder="little")[0]
            tail = u[whole:][differs]
            others[k:k + tail.size] = tail
            k += tail.size
        others = others[:k]
    else:
        differs = u != pattern
        others = u.take(np.flatnonzero(differs))  # (a gather: 4x boolean indexing at 18 %)
        mask = np.packbits(differs, bitorder="little")
    if order != ">u4":  # stored big-endian, as a raw capture holds them
        others = others.view(order).astype(">u4")
    return b"".join((HEADER.pack(MAGIC, n_tdc, n, first_word), mask,
                     memoryview(others).cast("B")))


def encode_sparse(index: np.ndarray, others: np.ndarray, n: int, first_word: int,
                  n_tdc: int) -> bytes:
    """The frame content :func:`encode` gives, from the words' sparse form (``index``:
    ascending places in the chunk of the words that differ from their no-hit word,
    ``others``: those words, native; ``stages.datapath.SparseWords``), as a chip's source
    has it: the mask is set from the indices, no pass over the chunk's words."""
    differs = np.zeros(n, bool)
    differs[index] = True
    return b"".join((HEADER.pack(MAGIC, n_tdc, n, first_word),
                     np.packbits(differs, bitorder="little"),
                     memoryview(np.asarray(others, np.uint32).astype(">u4")).cast("B")))


def _split_loop(u, pattern, mask, others, fill):
    """The kernel: ``mask`` (np.packbits' little bit order) of the words of ``u`` that
    differ from ``pattern``, and those words gathered into ``others`` (room for all of
    ``u``), their count in ``fill[0]``; one pass, no branch on the data (~1.1 ns a word on
    the 2-core VM). Whole bytes only: the last ``n % 8`` words are the caller's."""
    n = u.size
    k = 0
    for j in range(n // 8):  # a fixed inner loop, which the compiler unrolls
        byte = 0
        base = 8 * j
        for b in range(8):
            w = u[base + b]
            d = np.uint8(w != pattern[base + b])
            others[k] = w
            k += d
            byte |= d << b
        mask[j] = byte
    fill[0] = k


def _kernel():
    """The compiled kernel as a C function (stages.nativecode), or None (then numpy)."""
    import ctypes

    from stages import nativecode

    p, i64 = ctypes.c_void_p, ctypes.c_int64
    return nativecode.kernel("split", __file__, [p, i64, p, p, p, p], _build)


def warm() -> None:
    """Load (or, the first time on a host, compile) the kernel now."""
    _kernel()


def _build():
    import numba
    from numba import carray, types

    loop = numba.njit(nogil=True)(_split_loop)
    p = types.CPointer

    def c_split(u, n, pattern, mask, others, fill):
        loop(carray(u, (n,)), carray(pattern, (n,)), carray(mask, ((n + 7) // 8,)),
             carray(others, (n,)), carray(fill, (1,)))

    sig = types.void(p(types.uint32), types.int64, p(types.uint32), p(types.uint8),
                     p(types.uint32), p(types.int64))
    return numba.cfunc(sig, nopython=True)(c_split)


#: more TDCs than a frame may name (the chip's addresses are 8 bits): a header saying more
#: is damaged, and is refused before its pattern is built
MAX_TDC = 1 << 20
#: the most words a frame may hold: a frame is one batch (the daemon's are at most a few
#: MiB) and a header claiming more is refused before its mask or words are allocated (a
#: 16 KB file claiming 2^32 words must not take gigabytes: zstd expands zeros ~32 000-fold)
MAX_FRAME_WORDS = 1 << 26


def decode(content: bytes | memoryview, first_word: int | None = None,
           words: int | None = None, n_tdc: int | None = None) -> tuple[int, np.ndarray]:
    """``(first_word, words)`` of a frame's content, the words big-endian (``>u4``);
    FrameError when it is not well-formed or disagrees with the expected ``first_word``,
    ``words`` count (the index's) or ``n_tdc`` (a capture sidecar's)."""
    content = memoryview(content).cast("B")
    if content.nbytes < HEADER.size:
        raise FrameError(f"{content.nbytes} bytes, shorter than the frame header")
    magic, frame_tdc, n, first = HEADER.unpack_from(content)
    if magic != MAGIC:
        raise FrameError(f"not a zstd-nohit frame (magic {bytes(magic)!r})")
    if not 1 <= frame_tdc <= MAX_TDC or (n_tdc is not None and frame_tdc != n_tdc):
        raise FrameError(f"n_tdc {frame_tdc} in the frame header"
                         + (f", the sidecar says {n_tdc}" if n_tdc is not None else ""))
    n_tdc = frame_tdc
    if n > MAX_FRAME_WORDS:
        raise FrameError(f"the frame header claims {n} words, more than a frame may hold "
                         f"({MAX_FRAME_WORDS})")
    if words is not None and n != words:
        raise FrameError(f"the frame holds {n} words, the index says {words}")
    if first_word is not None and first != first_word:
        raise FrameError(f"the frame starts at word {first}, the index says {first_word}")
    nmask = -(-n // 8)
    rest = content.nbytes - HEADER.size - nmask
    if rest < 0 or rest % 4:
        raise FrameError(f"{content.nbytes} bytes do not hold a {n}-word mask and whole words")
    mask = np.frombuffer(content, np.uint8, nmask, HEADER.size)
    where = np.flatnonzero(np.unpackbits(mask, count=n, bitorder="little").view(bool))
    others = np.frombuffer(content, ">u4", rest // 4, HEADER.size + nmask)
    if where.size != others.size or (n % 8 and int(mask[-1]) >> (n % 8)):
        raise FrameError(f"the mask marks {where.size} words, {others.size} follow it")
    off = first % n_tdc
    out = _tile(n_tdc, n, ">u4")[off:off + n].view(">u4").copy()
    out[where] = others  # (a scatter by index: 2-3x boolean assignment at 18 %)
    return first, out


class FrameReader:
    """A segment of ``zstd-nohit`` frames read as the raw capture's bytes (``read``,
    ``readinto``, a context manager): what :class:`pipeline.io.capture.Capture` opens for
    ``NAME.bin.nhz``. A damaged frame raises (zstd's error, or FrameError)."""

    def __init__(self, path, n_tdc: int | None = None):
        import zstandard

        self.n_tdc = n_tdc
        self._fh = open(path, "rb")
        self._z = zstandard.ZstdDecompressor().stream_reader(self._fh, read_across_frames=True)
        self._buf = memoryview(b"")

    def _exact(self, n: int) -> bytes:
        parts, got = [], 0
        while got < n:
            b = self._z.read(n - got)
            if not b:
                break
            parts.append(b)
            got += len(b)
        return b"".join(parts)

    def _next_frame(self) -> bool:
        head = self._exact(HEADER.size)
        if not head:
            return False
        if len(head) < HEADER.size:
            raise FrameError(f"a frame header cut short ({len(head)} bytes)")
        magic, _, n, _ = HEADER.unpack(head)
        if magic != MAGIC:
            raise FrameError(f"not a zstd-nohit frame (magic {magic!r})")
        if n > MAX_FRAME_WORDS:
            raise FrameError(f"the frame header claims {n} words, more than a frame may hold "
                             f"({MAX_FRAME_WORDS})")
        mask = self._exact(-(-n // 8))
        if len(mask) < -(-n // 8):
            raise FrameError(f"a frame of {n} words cut short inside its mask")
        k = int(np.count_nonzero(np.unpackbits(np.frombuffer(mask, np.uint8), count=n,
                                               bitorder="little").view(bool)))
        others = self._exact(4 * k)
        self._buf = memoryview(decode(head + mask + others, n_tdc=self.n_tdc)[1]).cast("B")
        return True

    def readinto(self, buf) -> int:
        out = memoryview(buf).cast("B")
        got = 0
        while got < out.nbytes:
            if not self._buf.nbytes and not self._next_frame():
                break
            k = min(self._buf.nbytes, out.nbytes - got)
            out[got:got + k] = self._buf[:k]
            self._buf = self._buf[k:]
            got += k
        return got

    def read(self, n: int) -> bytes:
        b = bytearray(n)
        return bytes(b[:self.readinto(b)])

    def close(self) -> None:
        self._z.close()
        self._fh.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
