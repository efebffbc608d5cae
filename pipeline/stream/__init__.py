"""The live graph: the one generic ZeroMQ stage runner (``stage``), its framing and header
schemas (``wire``), fan-out by TDC range (``fanout``), heartbeats (``metrics``), CURVE keys
(``curve``), the FPGA's UDP datagram (``datagram``) and its ingest (``udp``), the journal
(``journal``) and the supervising daemon (``daemon``). Imports ``pipeline.io``,
``pipeline.offline`` (the range stage's calibration), ``stages`` and ``schemas``."""
