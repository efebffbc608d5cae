"""Contracts of the raw stream: word classes, raw-word batches and decoded-event batches."""

from __future__ import annotations

import pyarrow as pa

from schemas.constants import (  # noqa: F401  (re-exported: the contract's numbers)
    ARTIFACT,
    HIT,
    INVALID_PHASE,
    MALFORMED,
    N_CLASSES,
    N_CODES,
    N_CODES_2ND,
    NO_HIT,
    WORD_CLASSES,
)
from schemas.core import SchemaSpec, field

RAW_WORDS = SchemaSpec("raw_words", "1.0", (
    field("word", pa.uint32(), "", "raw 32-bit TDC word as a native integer (Table 5.1); "
          "word i of a stream belongs to cycle first_cycle + i // n_tdc"),
))

#: Raw words in sparse form: a message of ``n_words`` words (its header) carries only the
#: words that are not their position's plain no_hit word (marker bit 9 and the address,
#: nothing else; any other word is another class), with their index in the message's span.
#: The source sends chip words so between stages (docs/streaming.md "Sparse raw words").
RAW_SPARSE = SchemaSpec("raw_sparse", "1.0", (
    field("index", pa.uint32(), "", "index of the word in the message's span of n_words "
          "words, strictly ascending; word i of the span is stream word first_word + i"),
    field("word", pa.uint32(), "", "the raw 32-bit TDC word as a native integer; every word "
          "of the span not listed is its position's plain no_hit word"),
))

_CLASS_TYPE = pa.dictionary(pa.int8(), pa.string())

DECODED_EVENTS = SchemaSpec("decoded_events", "1.0", (
    field("cycle", pa.uint64(), "cycle", "DAQ cycle index of the word in its capture or run"),
    field("tdc", pa.uint16(), "", "TDC of the word's position in its cycle (0-based)"),
    field("word", pa.uint32(), "", "the raw word, kept so nothing is lost"),
    field("word_class", _CLASS_TYPE, "",
          "hit, no_hit, artifact, invalid_phase or malformed"),
    field("c1st", pa.uint8(), "VCO cycles", "first-stage VCO counter C1st (6 bits)"),
    field("p1st", pa.uint8(), "phase", "first-stage phase P1st decoded to 0..7; "
          "null for an invalid phase code or a malformed word", nullable=True),
    field("c2nd", pa.uint8(), "VCO cycles", "second-stage VCO counter C2nd (5 bits)"),
    field("p2nd", pa.uint8(), "phase", "second-stage phase P2nd decoded to 0..7; null when "
          "invalid", nullable=True),
    field("d1st", pa.uint16(), "LSB", "first-stage code 8*C1st+P1st (eq. 3.2); null when "
          "undecodable", nullable=True),
    field("d2nd", pa.uint16(), "LSB2", "second-stage code 8*C2nd+P2nd (eq. 3.3); null when "
          "undecodable", nullable=True),
))


def class_dictionary() -> pa.Array:
    """The dictionary of the ``word_class`` column, in code order."""
    return pa.array(WORD_CLASSES, pa.string())
