"""The runtime floor: everything that touches files, sockets, processes and the terminal.

Its rooms, each a subpackage, and what each may import (besides ``stages`` and ``schemas``,
which every room may use; ``tests/test_layers.py`` checks both rules):

- ``io``: files (captures, calibration directories, atomic writes, and real instruments'
  files: PicoQuant PTU, LinoSPAD2 raw words).
  Imports no other room.
- ``offline``: drivers over whole files (decode, histogram, calibrate, range, simulate).
  Imports ``io``.
- ``stream``: the live graph (stage runner, wire, UDP ingest, journal, daemon). Imports
  ``io`` and ``offline``.
- ``report``: figures, reports and the demo's checks. Imports ``io`` and ``offline``.
- ``view``: the live web page (``tcspc view``): reads the metrics PUB and the datasets,
  never sits in the stream. Imports ``io``, ``offline`` and ``stream``.
- ``cli``: the ``tcspc`` command line. Imports every room (heavy modules only inside the
  commands that use them).

Nothing here imports ``flows``.
"""
