"""Arrow schemas and file-format contracts. Imports pyarrow only.

Every dataset is defined once here, with a name, a version and units in field metadata.
"""

from schemas.core import SchemaSpec, field, validate
from schemas.errors import (
    CalibrationError,
    CaptureError,
    SchemaMismatch,
    SchemaVersionError,
    TcspcError,
)
from schemas.instruments import LINOSPAD2_EVENTS, PTU_T2_EVENTS, PTU_T3_EVENTS
from schemas.outputs import CALIBRATION_INL, CALIBRATION_TDC, HISTOGRAMS, RANGES
from schemas.words import (
    ARTIFACT,
    DECODED_EVENTS,
    HIT,
    INVALID_PHASE,
    MALFORMED,
    N_CLASSES,
    N_CODES,
    N_CODES_2ND,
    NO_HIT,
    RAW_WORDS,
    WORD_CLASSES,
)

ALL_SPECS = (RAW_WORDS, DECODED_EVENTS, HISTOGRAMS, CALIBRATION_TDC, CALIBRATION_INL, RANGES,
             PTU_T2_EVENTS, PTU_T3_EVENTS, LINOSPAD2_EVENTS)


def docs_markdown() -> str:
    """docs/schemas.md, generated from the specs (``make docs``; a test checks for drift)."""
    return "\n\n".join(spec.doc_table() for spec in ALL_SPECS) + "\n"


__all__ = [
    "ALL_SPECS", "ARTIFACT", "CALIBRATION_INL", "CALIBRATION_TDC", "CalibrationError",
    "CaptureError", "DECODED_EVENTS", "LINOSPAD2_EVENTS", "PTU_T2_EVENTS", "PTU_T3_EVENTS",
    "docs_markdown", "HISTOGRAMS", "HIT", "INVALID_PHASE",
    "MALFORMED",
    "N_CLASSES", "N_CODES", "N_CODES_2ND", "NO_HIT", "RANGES", "RAW_WORDS", "SchemaMismatch",
    "SchemaSpec", "SchemaVersionError", "TcspcError", "WORD_CLASSES", "field", "validate",
]
