"""The project's exception hierarchy: one base, mixed with the builtin each error resembles.

Catching ``TcspcError`` catches everything this package raises on purpose; catching the
builtin (``ValueError``, ``OSError``) keeps working for callers that do not know us.
"""

from __future__ import annotations


class TcspcError(Exception):
    """Base of every error raised on purpose by tcspc-lidar."""


class SchemaMismatch(TcspcError, ValueError):
    """A table or batch does not match the schema it claims (names the column and types)."""


class SchemaVersionError(TcspcError, ValueError):
    """A reader met a major schema version it does not know (names both versions)."""


class CaptureError(TcspcError, ValueError):
    """A raw capture (``.bin`` + ``.json``) is unreadable or inconsistent (names the file)."""


class Rejected(TcspcError, ValueError):
    """Input refused at an edge (a message, a datagram): ``reason`` is its class in the
    accounting (the rejection counters and the quarantine use it)."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason = reason


class CalibrationError(TcspcError, ValueError):
    """A calibration directory is missing, unreadable or inconsistent with the data."""
