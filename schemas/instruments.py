"""Event schemas of real instruments' files: PicoQuant PTU (T2, T3) and LinoSPAD2 raw words.

A decoded PTU file is one row per record that carries an event: a photon on an input channel
or a marker (an external TTL edge); overflow (wrap) records are folded into the times and
counted, not kept. ``kind`` tells the two event classes apart.
"""

from __future__ import annotations

import pyarrow as pa

from schemas.constants import PTU_MAGIC  # noqa: F401  (re-exported)
from schemas.core import SchemaSpec, field

#: the values of ``kind`` in the PTU event datasets
PHOTON, MARKER = 0, 1
EVENT_KINDS = ("photon", "marker")

PTU_T2_EVENTS = SchemaSpec("ptu_t2_events", "1.0", (
    field("kind", pa.uint8(), "", "0 = photon, 1 = marker"),
    field("channel", pa.uint8(), "", "input channel (0-based) of a photon, or the marker "
          "bits (1..15) of a marker"),
    field("time_ps", pa.int64(), "ps", "absolute arrival time since the start of the file, "
          "overflow-corrected (timetag x the file's resolution)"),
))

PTU_T3_EVENTS = SchemaSpec("ptu_t3_events", "1.0", (
    field("kind", pa.uint8(), "", "0 = photon, 1 = marker"),
    field("channel", pa.uint8(), "", "input channel (0-based) of a photon, or the marker "
          "bits (1..15) of a marker"),
    field("nsync", pa.uint64(), "sync", "sync (laser) period number since the start of the "
          "file, overflow-corrected"),
    field("dtime", pa.uint16(), "bin", "start-stop time in the sync period, in units of the "
          "file's resolution (0 for a marker)"),
))

LINOSPAD2_EVENTS = SchemaSpec("linospad2_events", "1.0", (
    field("cycle", pa.uint32(), "cycle", "acquisition cycle (0-based) in the file"),
    field("tdc", pa.uint8(), "", "TDC (0..63)"),
    field("pixel", pa.uint16(), "", "pixel (0..255): 4 x TDC + the pixel bits (2212b) or "
          "TDC + 64 x the pixel bits (2212s)"),
    field("code", pa.uint32(), "17.857 ps", "time code (bits 27:0): 2.5 ns clock x 140 + "
          "fine code"),
    field("fine", pa.uint8(), "", "fine (carry-chain) code, code mod 140"),
))
