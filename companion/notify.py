"""systemd notify protocol (sd_notify(3)): READY=1, STATUS=..., EXTEND_TIMEOUT_USEC=..., WATCHDOG=1, STOPPING=1.

One datagram per call to the AF_UNIX socket named by ``$NOTIFY_SOCKET`` — a filesystem path, or an
abstract socket when it starts with ``@``. Written with the socket module: the protocol is a single
``sendto`` and keeping it here lets us support abstract sockets and report send errors ourselves.
Outside systemd (no ``$NOTIFY_SOCKET``) every call is a no-op that returns False.
"""
from __future__ import annotations

import logging
import os
import socket
from typing import Mapping

log = logging.getLogger(__name__)


def _address(environ: Mapping[str, str]) -> str | None:
    addr = environ.get("NOTIFY_SOCKET", "")
    if not addr:
        return None
    if addr[0] not in "/@":
        log.warning("NOTIFY_SOCKET=%r is neither a path nor an abstract socket; not notifying", addr)
        return None
    return "\0" + addr[1:] if addr[0] == "@" else addr


def notify(state: str, environ: Mapping[str, str] | None = None) -> bool:
    """Send ``state`` (newline-separated VAR=value lines); True when a datagram was sent."""
    addr = _address(os.environ if environ is None else environ)
    if addr is None:
        return False
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            sock.sendto(state.encode("utf-8"), addr)
    except OSError as e:
        log.warning("sd_notify(%r) failed: %s", state.split("\n")[0], e)
        return False
    return True


def ready(status: str | None = None, environ: Mapping[str, str] | None = None) -> bool:
    """Startup finished (Type=notify units leave 'activating')."""
    return notify("READY=1" + (f"\nSTATUS={status}" if status else ""), environ)


def status(text: str, environ: Mapping[str, str] | None = None) -> bool:
    """One-line status shown by ``systemctl status``."""
    return notify(f"STATUS={text.splitlines()[0] if text else ''}", environ)


def extend_timeout(seconds: float, environ: Mapping[str, str] | None = None) -> bool:
    """Startup goes on for up to ``seconds`` more from now (EXTEND_TIMEOUT_USEC, systemd >= 236):
    sent while the service waits on something outside it, so TimeoutStartSec does not kill it."""
    return notify(f"EXTEND_TIMEOUT_USEC={int(seconds * 1e6)}", environ)


def watchdog(environ: Mapping[str, str] | None = None) -> bool:
    """Keep-alive ping; send only while the service really makes progress."""
    return notify("WATCHDOG=1", environ)


def stopping(environ: Mapping[str, str] | None = None) -> bool:
    """Clean shutdown has begun."""
    return notify("STOPPING=1", environ)


def watchdog_interval_s(environ: Mapping[str, str] | None = None) -> float | None:
    """How often to ping: half of ``$WATCHDOG_USEC`` (sd_watchdog_enabled(3)), or None when off.

    None also when ``$WATCHDOG_PID`` names another process (the variable was inherited).
    """
    env = os.environ if environ is None else environ
    usec = env.get("WATCHDOG_USEC", "")
    if not usec:
        return None
    pid = env.get("WATCHDOG_PID", "")
    if pid and pid != str(os.getpid()):
        return None
    try:
        value = int(usec)
    except ValueError:
        log.warning("WATCHDOG_USEC=%r is not an integer; watchdog pings disabled", usec)
        return None
    return value / 2e6 if value > 0 else None
