"""Process logging: human-readable lines or one JSON object per line, plus structured events.

``setup_logging(cfg)`` configures the root logger once (stderr, which journald captures).
``log_event(logger, "switch", source="slam", reason="gnss_jammed")`` writes an event with fields:
text mode appends ``key=value`` pairs; JSON mode puts them as top-level keys next to
``t_wall`` (ISO-8601 UTC), ``t_mono_s``, ``level``, ``logger``, ``msg`` and ``event``.
"""
from __future__ import annotations

import datetime as dt
import json
import logging
import sys
import time
from typing import Any, TextIO

from companion.config import LoggingConfig

_EVENT_ATTR = "terraslam_event"


def _jsonable(value: Any) -> Any:
    if hasattr(value, "tolist"):  # numpy scalars and arrays
        return value.tolist()
    if hasattr(value, "value") and hasattr(value, "name"):  # enums
        return value.value
    return str(value)


class JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {
            "t_wall": dt.datetime.fromtimestamp(record.created, dt.timezone.utc).isoformat(timespec="milliseconds"),
            "t_mono_s": round(getattr(record, "t_mono_s", time.monotonic()), 6),
            "level": record.levelname,
            "logger": record.name,
            "msg": record.getMessage(),
        }
        event = getattr(record, _EVENT_ATTR, None)
        if event is not None:
            name, fields = event
            out["event"] = name
            out.update({k: v for k, v in fields.items() if k not in out})
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out, default=_jsonable, ensure_ascii=False)


class TextFormatter(logging.Formatter):
    def __init__(self) -> None:
        super().__init__("%(asctime)s %(levelname)-7s %(name)s: %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        line = super().format(record)
        event = getattr(record, _EVENT_ATTR, None)
        if event is not None:
            name, fields = event
            line += f" [{name}]" + "".join(f" {k}={v}" for k, v in fields.items())
        return line


def setup_logging(cfg: LoggingConfig, stream: TextIO | None = None) -> logging.Handler:
    """Replace the root logger's handlers with one stderr (or ``stream``) handler per ``cfg``."""
    handler = logging.StreamHandler(stream or sys.stderr)
    handler.setFormatter(JsonFormatter() if cfg.json_logs else TextFormatter())
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(cfg.level)
    logging.captureWarnings(True)
    return handler


def log_event(logger: logging.Logger, event: str, message: str | None = None, level: int = logging.INFO, **fields: Any) -> None:
    """A structured event (e.g. ``switch``, ``stall``, ``stage_restart``) with its fields."""
    logger.log(
        level,
        message or event,
        extra={_EVENT_ATTR: (event, fields), "t_mono_s": time.monotonic()},
        stacklevel=2,
    )
