"""The daemon's log lines (issue 38.8): a UTC timestamp, a level and the stage each line is
about, as text or as JSON lines for a log shipper (``tcspc daemon --log-json`` or
``[log] format = "json"``).

    2026-12-05T07:41:02.318Z WARNING daemon: histogram-1: died (exit -9); restart 1 in 0.5 s ...
    {"ts": "2026-12-05T07:41:02.318Z", "level": "WARNING", "stage": "histogram-1", "msg": "..."}

Built on the standard library's ``logging`` (a handler on stderr, a formatter per format).
The supervisor says what happened in one sentence; the level follows what the sentence
reports (a death, a freeze, a pause, a problem: WARNING; a failed run: ERROR), and the
stage is the one the sentence starts with (``histogram-1: ...``), else ``daemon``.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import re
import sys

#: a line about one stage starts with its name
_STAGE = re.compile(r"^(source|sink|range|view|histogram-\d+): ")
_ERROR = ("giving up", "failed", "no accounting")
_WARNING = ("died", "frozen", "paused", "not written", "not bound", "incomplete",
            "unbalanced", "lost", "nothing taken", "rebuilt", "withheld",
            "restarted", "problem", "not updated", "ended (exit")


def level_of(msg: str) -> int:
    low = msg.lower()
    if any(w.lower() in low for w in _ERROR):
        return logging.ERROR
    if any(w.lower() in low for w in _WARNING):
        return logging.WARNING
    return logging.INFO


def stage_of(msg: str) -> str:
    m = _STAGE.match(msg)
    return m.group(1) if m else "daemon"


def _ts(record: logging.LogRecord) -> str:
    return dt.datetime.fromtimestamp(record.created, dt.UTC).strftime(
        "%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"


class TextFormatter(logging.Formatter):
    def format(self, record):
        return f"{_ts(record)} {record.levelname} daemon: {record.getMessage()}"


class JsonFormatter(logging.Formatter):
    def format(self, record):
        return json.dumps({"ts": _ts(record), "level": record.levelname,
                           "stage": getattr(record, "stage", "daemon"),
                           "msg": record.getMessage()}, ensure_ascii=False)


def daemon_log(fmt: str = "text", stream=None):
    """``log(msg, level=None)``: one line on ``stream`` (stderr) in ``fmt`` ("text" or
    "json"); the level from the message unless given."""
    logger = logging.getLogger("tcspc.daemon")
    logger.propagate = False
    logger.setLevel(logging.INFO)
    for h in list(logger.handlers):
        logger.removeHandler(h)
    handler = logging.StreamHandler(stream or sys.stderr)
    handler.setFormatter(JsonFormatter() if fmt == "json" else TextFormatter())
    logger.addHandler(handler)

    def log(msg: str, level: int | None = None) -> None:
        msg = str(msg)
        logger.log(level_of(msg) if level is None else level, "%s", msg,
                   extra={"stage": stage_of(msg)})

    return log
