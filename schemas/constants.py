"""The numbers of the contracts, without pyarrow: word classes, code counts, file magics.

The modules that hold the Arrow schemas re-export these (``schemas.words``,
``schemas.instruments``); the hot path imports them from here, so histogramming a capture
imports no pyarrow (50-90 ms): the command imports it when it writes its file.
"""

from __future__ import annotations

#: Word classes, in the order of their integer codes. Classification precedence is
#: ``malformed > invalid_phase > no_hit > artifact > hit`` (docs/design.md, "Raw word").
WORD_CLASSES: tuple[str, ...] = ("hit", "no_hit", "artifact", "invalid_phase", "malformed")
HIT, NO_HIT, ARTIFACT, INVALID_PHASE, MALFORMED = range(5)
N_CLASSES = len(WORD_CLASSES)

#: Codes of the first-stage TDC: D1st = 8*C1st + P1st in 0..511 (eq. 3.2).
N_CODES = 512
#: Second-stage raw codes: D2nd = 8*C2nd + P2nd in 0..255 (eq. 3.3).
N_CODES_2ND = 256

#: A PicoQuant PTU file's first 8 bytes (its format's magic).
PTU_MAGIC = b"PQTTTR\0\0"
