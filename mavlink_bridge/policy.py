"""Switch policy: STANDBY (GNSS trusted) ⇄ ACTIVE (we are the position source).

Safety first and no flapping:
- Taking over is immediate when GNSS is LOST or UNTRUSTED (fix loss, spoofing, glitch, jamming),
  after ``degraded_takeover_s`` of DEGRADED. The monitor already needs ``stale_after_s`` to call
  silence a loss, so fix-loss detection is bounded by that plus one receive tick.
- Handing back needs GNSS GOOD (and agreeing with vision: the spoofing test is part of GOOD) for
  ``handback_good_s`` without interruption AND ``min_dwell_s`` in ACTIVE.
- While the link to the autopilot is down nothing changes (we cannot see its GNSS).
"""
from __future__ import annotations

import enum
from dataclasses import dataclass, field

from mavlink_bridge.config import SwitchingConfig
from mavlink_bridge.types import GnssQuality, GnssStatus


class BridgeState(enum.Enum):
    STANDBY = "standby"  # GNSS trusted: we compute, log and optionally feed a secondary source
    ACTIVE = "active"    # GNSS untrusted: we are the position source


@dataclass(frozen=True)
class SwitchEvent:
    t_s: float
    from_state: BridgeState
    to_state: BridgeState
    reason: str


@dataclass
class SwitchPolicy:
    cfg: SwitchingConfig
    state: BridgeState = BridgeState.STANDBY
    entered_s: float | None = None
    events: list[SwitchEvent] = field(default_factory=list)
    _good_since_s: float | None = None
    _degraded_since_s: float | None = None

    def update(self, status: GnssStatus, link_up: bool = True, have_fix: bool = True) -> SwitchEvent | None:
        """Feed the monitor's verdict; returns the transition it caused, if any. ``have_fix``: we
        have a fresh fix to offer. A lost or degraded receiver is taken over only then: an
        autopilot switched to a source with nothing in it gains nothing (at boot, before the
        receiver's first fix, it would only fight its acquisition); an untrusted (spoofed) one is
        taken over regardless, as following it is worse than dead reckoning."""
        now = status.t_s
        if self.entered_s is None:
            self.entered_s = now
        if not link_up:
            self._good_since_s = None
            return None
        q = status.quality
        self._good_since_s = (self._good_since_s if self._good_since_s is not None else now) if q is GnssQuality.GOOD else None
        self._degraded_since_s = (self._degraded_since_s if self._degraded_since_s is not None else now) if q is GnssQuality.DEGRADED else None
        why = "; ".join(status.reasons)
        if self.state is BridgeState.STANDBY:
            if q is GnssQuality.UNTRUSTED or (q is GnssQuality.LOST and have_fix):
                return self._go(BridgeState.ACTIVE, now, f"GNSS {q.value}: {why}")
            if q is GnssQuality.DEGRADED and have_fix and now - self._degraded_since_s >= self.cfg.degraded_takeover_s:
                return self._go(BridgeState.ACTIVE, now, f"GNSS degraded for {now - self._degraded_since_s:.1f} s: {why}")
            return None
        good_for = now - self._good_since_s if self._good_since_s is not None else 0.0
        if (
            self._good_since_s is not None
            and good_for >= self.cfg.handback_good_s
            and now - self.entered_s >= self.cfg.min_dwell_s
        ):
            return self._go(BridgeState.STANDBY, now, f"GNSS good and agreeing for {good_for:.1f} s")
        return None

    def _go(self, to: BridgeState, now: float, reason: str) -> SwitchEvent:
        ev = SwitchEvent(now, self.state, to, reason)
        self.events.append(ev)
        self.state, self.entered_s = to, now
        self._good_since_s = None
        return ev
