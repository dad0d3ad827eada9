"""Worker logs: one JSON object per line (ts, level, logger, msg, pid and every ``extra``
field) when stderr is not a terminal, short text lines when it is."""

from __future__ import annotations

import json
import logging
import sys
import time

__all__ = ["JsonFormatter", "configure_logging"]

_STD_ATTRS = set(vars(logging.makeLogRecord({}))) | {"message", "asctime"}


class JsonFormatter(logging.Formatter):
    """One JSON object per line: ts, level, logger, msg and every ``extra`` field."""

    def format(self, record: logging.LogRecord) -> str:
        out = {"ts": round(record.created, 3), "level": record.levelname.lower(), "logger": record.name,
               "msg": record.getMessage(), "pid": record.process}
        out.update({k: v for k, v in vars(record).items() if k not in _STD_ATTRS})
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out, default=str)


class _TextFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        extra = " ".join(f"{k}={v}" for k, v in vars(record).items() if k not in _STD_ATTRS)
        return f"{time.strftime('%H:%M:%S')} {record.levelname:<7} {record.getMessage()} {extra}".rstrip()


def configure_logging(level: int = logging.INFO, stream=None) -> None:
    """JSON lines on non-terminals, short text lines on a terminal."""
    stream = stream or sys.stderr
    handler = logging.StreamHandler(stream)
    handler.setFormatter(_TextFormatter() if stream.isatty() else JsonFormatter())
    root = logging.getLogger("bssrdf")
    root.handlers[:] = [handler]
    root.setLevel(level)
    root.propagate = False
