"""The ingest: the FPGA's UDP datagrams in, journaled raw-word batches out.

Binds 127.0.0.1 unless told otherwise. Every datagram is accounted for: taken (its words
journaled to capture segments before they are passed on), a duplicate (counted, dropped),
late (it came after its reorder window closed: counted and quarantined), or rejected by
reason and quarantined. UDP reorders and duplicates, so datagrams are reassembled by first
cycle in a bounded reorder window and each cycle is journaled once, in order; cycles no
datagram brought are a gap (counted), and sequence numbers never seen are lost datagrams.
Every header field is bounded against the run: a cycle or sequence number beyond the
window (``max_jump_cycles``, ``max_jump_datagrams``), another TDC count or gate, is a
rejected datagram, never a gap to fill.

Rooms: :mod:`.order` (sequence numbers and cycles, the reorder window), :mod:`.reference`
(which stream is the run's), :mod:`.senders` (whose datagrams are read), :mod:`.resume` (a
restarted ingest), :mod:`.ingest` (the socket, the threads, the journal and the messages).
"""

from pipeline.stream.udp.ingest import (
    BATCH_WORDS,
    FLUSH_S,
    GATE_PS,
    RCVBUF_BYTES,
    REORDER_LINGER_S,
    RING_DATAGRAMS,
    RX_BATCH,
    SEND_QUEUE,
    IngestStats,
    run_udp_ingest,
    udp_socket,
)
from pipeline.stream.udp.order import (
    MAX_JUMP_CYCLES,
    MAX_JUMP_DATAGRAMS,
    REORDER_WINDOW,
    Reassembler,
    _signed32,
    consistent,
    max_cycles,
)
from pipeline.stream.udp.reference import QUORUM, QUORUM_HOLD, Reference
from pipeline.stream.udp.resume import resume_state
from pipeline.stream.udp.senders import Senders, parse_peers

__all__ = ["BATCH_WORDS", "FLUSH_S", "GATE_PS", "MAX_JUMP_CYCLES", "MAX_JUMP_DATAGRAMS",
           "QUORUM", "QUORUM_HOLD", "RCVBUF_BYTES", "REORDER_LINGER_S", "REORDER_WINDOW",
           "RING_DATAGRAMS", "RX_BATCH", "SEND_QUEUE", "IngestStats", "Reassembler",
           "Reference", "_signed32", "consistent", "max_cycles", "resume_state",
           "run_udp_ingest", "udp_socket", "Senders", "parse_peers"]
