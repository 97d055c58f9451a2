"""MAVLink 2 link: pymavlink connection (serial / UDP / TCP), signing, thread-safe send,
receive that never raises on garbage, reconnect with exponential back-off.
"""
from __future__ import annotations

import logging
import os
import stat
import threading
import time
from pathlib import Path
from typing import Callable

os.environ.setdefault("MAVLINK20", "1")  # must precede the pymavlink import: MAVLink 2 framing

from pymavlink import mavutil  # noqa: E402

log = logging.getLogger(__name__)

DIALECT = "ardupilotmega"  # superset of common: ArduPilot commands + PX4-used common messages


class SigningKeyError(ValueError):
    """The signing key file is missing, unsafe or malformed."""


def load_signing_key(path: Path) -> bytes:
    """32-byte MAVLink 2 signing secret from ``path`` (32 raw bytes or 64 hex characters).

    The file must not be readable by group/others (mode 0600 or stricter)."""
    path = Path(path).expanduser()
    try:
        st = path.stat()
    except OSError as e:
        raise SigningKeyError(f"mavlink.signing_key_file {path}: cannot read ({e.strerror})") from e
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise SigningKeyError(
            f"mavlink.signing_key_file {path}: permissions {stat.S_IMODE(st.st_mode):04o} are too open; "
            "run `chmod 600` on it"
        )
    data = path.read_bytes()
    if len(data) == 32:
        return data
    text = data.strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    raise SigningKeyError(f"mavlink.signing_key_file {path}: expected 32 raw bytes or 64 hex characters, got {len(data)} bytes")


def open_connection(url: str, baud: int, source_system: int, source_component: int,
                    signing_key: bytes | None = None, allow_unsigned: bool = False):
    """A pymavlink connection speaking MAVLink 2; with a key, outgoing messages are signed and
    unsigned incoming ones rejected unless ``allow_unsigned``."""
    conn = mavutil.mavlink_connection(
        url, baud=baud, source_system=source_system, source_component=source_component,
        dialect=DIALECT, autoreconnect=True, robust_parsing=True,
        retries=0, reconnect_delay=0.1,  # one quick attempt: Link owns the back-off, pymavlink must not block
    )
    conn.mav.WIRE_PROTOCOL_VERSION = "2.0"
    if signing_key is not None:
        conn.setup_signing(
            signing_key, sign_outgoing=True,
            allow_unsigned_callback=(lambda _mav, _msgid: True) if allow_unsigned else None,
        )
    return conn


class Link:
    """One connection with a send lock (the hot path and the receive thread both send) and
    reconnect-on-error (serial unplugged, TCP peer gone) with back-off up to ``reconnect_max_s``."""

    def __init__(self, url: str, baud: int, source_system: int, source_component: int,
                 signing_key: bytes | None = None, allow_unsigned: bool = False, reconnect_max_s: float = 8.0,
                 tap: Callable[[bytes], None] | None = None):
        """``tap``: called with the wire bytes of every message sent and every valid message
        received (the flight recorder's telemetry log); it must not block or raise."""
        self._args = (url, baud, source_system, source_component, signing_key, allow_unsigned)
        self._tap = tap
        self._send_lock = threading.Lock()
        self._reconnect_max_s = reconnect_max_s
        self._backoff_s = 0.25
        self._next_try_s = 0.0
        self.conn = None
        self.rejected = 0   # frames dropped by the parser (bad CRC, bad signature, garbage)
        self.reconnects = 0
        self._open()

    @property
    def mav(self):
        return self.conn.mav

    def _open(self) -> bool:
        try:
            self.conn = open_connection(*self._args)
            self._backoff_s = 0.25
            return True
        except (OSError, ValueError) as e:  # serial.SerialException is an OSError
            self.conn = None
            self._next_try_s = time.monotonic() + self._backoff_s
            log.warning("MAVLink %s: cannot open (%s); retrying in %.1f s", self._args[0], e, self._backoff_s)
            self._backoff_s = min(self._backoff_s * 2, self._reconnect_max_s)
            return False

    def _drop(self, err: Exception) -> None:
        log.warning("MAVLink %s: link error (%s); reconnecting", self._args[0], err)
        try:
            self.conn.close()
        except Exception:  # closing a broken port may fail again; it is being replaced anyway
            pass
        self.conn = None
        self.reconnects += 1
        self._next_try_s = time.monotonic()

    def send(self, msg) -> bool:
        """Encode and write one message; False if the link is down (never raises)."""
        with self._send_lock:
            if self.conn is None:
                return False
            try:
                self.conn.mav.send(msg)
            except OSError as e:
                self._drop(e)
                return False
        if self._tap is not None:
            self._tap(msg.get_msgbuf())
        return True

    def recv(self, timeout_s: float):
        """Next valid message or None (timeout, garbage, bad signature, link down)."""
        if self.conn is None:
            if time.monotonic() < self._next_try_s:
                time.sleep(min(timeout_s, self._next_try_s - time.monotonic()))
                return None
            with self._send_lock:
                if not self._open():
                    return None
        try:
            msg = self.conn.recv_match(blocking=True, timeout=timeout_s)
        except OSError as e:
            with self._send_lock:
                self._drop(e)
            return None
        except Exception as e:  # pymavlink raises assorted errors on malformed input: drop the frame
            self.rejected += 1
            log.debug("MAVLink parse error dropped: %s", e)
            return None
        if msg is None:
            return None
        if msg.get_type() == "BAD_DATA":
            self.rejected += 1
            return None
        if self._tap is not None:
            self._tap(msg.get_msgbuf())
        return msg

    def close(self) -> None:
        with self._send_lock:
            if self.conn is not None:
                self.conn.close()
                self.conn = None
