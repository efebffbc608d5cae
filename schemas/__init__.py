"""Arrow schemas and file-format contracts. Imports pyarrow only.

Every dataset is defined once here, with a name, a version and units in field metadata.
The names below are imported from their submodules when first asked for (PEP 562): the
errors and the contract's numbers (``schemas.errors``, ``schemas.constants``) do not
import pyarrow, so the hot path can use them before pyarrow is loaded.
"""

from __future__ import annotations

import importlib

_WHERE = {  # name: the submodule that defines it
    **dict.fromkeys(("SchemaSpec", "field", "validate"), "core"),
    **dict.fromkeys(("CalibrationError", "CaptureError", "SchemaMismatch",
                     "SchemaVersionError", "TcspcError"), "errors"),
    **dict.fromkeys(("LINOSPAD2_EVENTS", "PTU_T2_EVENTS", "PTU_T3_EVENTS"), "instruments"),
    **dict.fromkeys(("CALIBRATION_INL", "CALIBRATION_TDC", "HISTOGRAMS", "RANGES"),
                    "outputs"),
    **dict.fromkeys(("DECODED_EVENTS", "RAW_SPARSE", "RAW_WORDS"), "words"),
    "PIXEL_GEOMETRY": "geometry",
    **dict.fromkeys(("ARTIFACT", "HIT", "INVALID_PHASE", "MALFORMED", "N_CLASSES", "N_CODES",
                     "N_CODES_2ND", "NO_HIT", "WORD_CLASSES"), "constants"),
}


def __getattr__(name: str):
    if name == "ALL_SPECS":
        from schemas.geometry import PIXEL_GEOMETRY
        from schemas.instruments import LINOSPAD2_EVENTS, PTU_T2_EVENTS, PTU_T3_EVENTS
        from schemas.outputs import CALIBRATION_INL, CALIBRATION_TDC, HISTOGRAMS, RANGES
        from schemas.words import DECODED_EVENTS, RAW_SPARSE, RAW_WORDS

        value = (RAW_WORDS, RAW_SPARSE, DECODED_EVENTS, HISTOGRAMS, CALIBRATION_TDC,
                 CALIBRATION_INL, RANGES, PTU_T2_EVENTS, PTU_T3_EVENTS, LINOSPAD2_EVENTS,
                 PIXEL_GEOMETRY)
    elif name in _WHERE:
        value = getattr(importlib.import_module(f"schemas.{_WHERE[name]}"), name)
    else:
        raise AttributeError(f"module 'schemas' has no attribute {name!r}")
    globals()[name] = value  # asked once
    return value


def docs_markdown() -> str:
    """docs/schemas.md, generated from the specs (``make docs``; a test checks for drift)."""
    return "\n\n".join(spec.doc_table() for spec in __getattr__("ALL_SPECS")) + "\n"


__all__ = ["ALL_SPECS", "docs_markdown", *_WHERE]


def __dir__() -> list[str]:
    return sorted(__all__)
