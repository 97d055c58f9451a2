"""Bridge benchmark: message rates achieved at the (simulated) autopilot, fix-to-wire latency,
and GNSS-loss / spoofing detection times. Real pymavlink over UDP loopback.

    python -m mavlink_bridge.bench [--seconds 3] [--frame-hz 30]

``run_rates`` and ``run_detection`` are what ``terraslam bench`` calls.
"""
from __future__ import annotations

import argparse
import logging
import time
from dataclasses import dataclass

import numpy as np

from mavlink_bridge.bridge import Bridge
from mavlink_bridge.config import MavlinkConfig, SwitchingConfig
from mavlink_bridge.policy import BridgeState
from mavlink_bridge.scenario import Flight
from mavlink_bridge.sim_autopilot import SimAutopilot

#: (autopilot, output, rate_hz): the recommended setups of docs/AUTOPILOTS.md
SETUPS = (
    ("ardupilot", "gps_input", 10.0),
    ("ardupilot", "odometry", 30.0),
    ("px4", "odometry", 30.0),
    ("px4", "vision_position_estimate", 30.0),
    ("px4", "global_position_sensor", 10.0),
    ("px4", "hil_gps", 10.0),
)
MSG = {"gps_input": "GPS_INPUT", "odometry": "ODOMETRY", "vision_position_estimate": "VISION_POSITION_ESTIMATE",
       "global_position_sensor": "GLOBAL_POSITION_SENSOR", "hil_gps": "HIL_GPS"}


@dataclass(frozen=True)
class RateResult:
    autopilot: str
    output: str
    target_hz: float
    sent_hz: float
    accepted_hz: float          # what the simulated autopilot accepted for fusion
    latency_p50_ms: float
    latency_p99_ms: float
    latency_max_ms: float
    n: int


@dataclass(frozen=True)
class DetectionResult:
    autopilot: str
    event: str                  # "fix lost (fix_type 0)" | "receiver silent" | "spoofed 10 m"
    detect_s: float             # event injected → bridge ACTIVE


def _pump(sim, bridge, flight, t0, seconds, frame_hz, gnss="good", stop_when=None):
    dt = 1.0 / frame_hz
    gnss_every = max(1, round(frame_hz / 5.0))
    end = time.monotonic() + seconds
    k = 0
    while time.monotonic() < end:
        now = time.monotonic()
        t = now - t0
        if k % gnss_every == 0:
            if gnss == "good":
                sim.feed_gnss(flight.gnss(now, t))
            elif gnss == "lost":
                sim.feed_gnss(flight.gnss_lost(now))
            elif gnss == "spoofed":
                sim.feed_gnss(flight.gnss(now, t, offset_ned_m=(0.0, 10.0, 0.0)))
        bridge.submit_fix(flight.fix(now, t, k))
        k += 1
        if stop_when is not None and stop_when():
            return
        time.sleep(max(0.0, dt - (time.monotonic() - now)))


def _rig(autopilot: str, output: str, rate_hz: float, sw: SwitchingConfig | None = None):
    params = {"GPS_AUTO_SWITCH": 0} if autopilot == "ardupilot" else {}
    sim = SimAutopilot(autopilot, ekf_start_s=0.2, params=params).start()
    cfg = MavlinkConfig(connect=f"udpout:127.0.0.1:{sim.port}", autopilot=autopilot, output=output, rate_hz=rate_hz)
    return sim, Bridge(cfg, sw or SwitchingConfig()).start()


def _sim_process(personality: str, params: dict, t0: float, cmd_q, out_q) -> None:
    """Simulated autopilot + 5 Hz receiver in its own process, so its threads do not compete with
    the bridge for the GIL (a real autopilot is another machine). Answers "count" with its accepted
    counts until "stop"."""
    import queue

    sim = SimAutopilot(personality, ekf_start_s=0.2, params=params).start()
    out_q.put(sim.port)
    flight = Flight()
    try:
        while True:
            now = time.monotonic()  # CLOCK_MONOTONIC: shared with the parent process
            sim.feed_gnss(flight.gnss(now, now - t0))
            try:
                cmd = cmd_q.get(timeout=0.2)
            except queue.Empty:
                continue
            out_q.put(dict(sim.received().accepted))
            if cmd == "stop":
                return
    finally:
        sim.close()


def run_rates(autopilot: str, output: str, rate_hz: float, seconds: float = 3.0, frame_hz: float = 30.0) -> RateResult:
    """Fixes submitted at ``frame_hz`` for ``seconds``; rates sent / accepted and fix-to-wire latency
    (submit_fix entry → datagram written) of the bridge, with the autopilot in another process."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    cmd_q, out_q = ctx.Queue(), ctx.Queue()
    t0 = time.monotonic()
    params = {"GPS_AUTO_SWITCH": 0} if autopilot == "ardupilot" else {}
    proc = ctx.Process(target=_sim_process, args=(autopilot, params, t0, cmd_q, out_q), daemon=True)
    proc.start()
    bridge = None
    try:
        port = out_q.get(timeout=30)
        cfg = MavlinkConfig(connect=f"udpout:127.0.0.1:{port}", autopilot=autopilot, output=output, rate_hz=rate_hz)
        bridge = Bridge(cfg, SwitchingConfig()).start()
        flight, dt = Flight(), 1.0 / frame_hz

        def frames(duration):
            end = time.monotonic() + duration
            while time.monotonic() < end:
                now = time.monotonic()
                bridge.submit_fix(flight.fix(now, now - t0))
                time.sleep(max(0.0, dt - (time.monotonic() - now)))
        frames(1.5)  # link up, EKF origin known
        cmd_q.put("count")
        acc0 = out_q.get(timeout=10).get(MSG[output], 0)
        sent0, n_lat0, t1 = bridge.stats().sent[MSG[output]], len(bridge.stats().fix_to_wire_s), time.monotonic()
        frames(seconds)
        span = time.monotonic() - t1
        time.sleep(0.05)
        cmd_q.put("stop")
        acc1 = out_q.get(timeout=10).get(MSG[output], 0)
        st = bridge.stats()
        lat_ms = np.asarray(st.fix_to_wire_s[n_lat0:]) * 1e3
        return RateResult(
            autopilot, output, rate_hz, (st.sent[MSG[output]] - sent0) / span, (acc1 - acc0) / span,
            float(np.percentile(lat_ms, 50)), float(np.percentile(lat_ms, 99)), float(lat_ms.max()), len(lat_ms),
        )
    finally:
        if bridge is not None:
            bridge.close()
        proc.join(timeout=5)
        if proc.is_alive():
            proc.terminate()


def run_detection(autopilot: str, event: str) -> DetectionResult:
    """Time from injecting ``event`` (lost | silent | spoofed) until the bridge takes over."""
    output = "gps_input" if autopilot == "ardupilot" else "odometry"
    sim, bridge = _rig(autopilot, output, 20.0)
    flight, t0 = Flight(), time.monotonic()
    try:
        _pump(sim, bridge, flight, t0, 3.0, 20.0)  # link up and judged (grace of stale_after_s after link-up)
        t_event = time.monotonic()
        _pump(sim, bridge, flight, t0, 8.0, 20.0, gnss=event, stop_when=lambda: bridge.state is BridgeState.ACTIVE)
        ev = bridge.events()
        detect = ev[0].t_s - t_event if ev else float("inf")
        label = {"lost": "fix lost (fix_type 0)", "silent": "receiver silent", "spoofed": "spoofed 10 m"}[event]
        return DetectionResult(autopilot, label, detect)
    finally:
        bridge.close()
        sim.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="measurement time per setup")
    ap.add_argument("--frame-hz", type=float, default=30.0, help="rate of submit_fix calls (camera frames)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)  # switch events are the measurement here, not log lines
    print(f"{'autopilot':10} {'output':26} {'target':>7} {'sent':>7} {'fused':>7} {'P50 ms':>7} {'P99 ms':>7} {'max ms':>7} {'n':>5}")
    for autopilot, output, hz in SETUPS:
        r = run_rates(autopilot, output, hz, args.seconds, args.frame_hz)
        print(f"{r.autopilot:10} {r.output:26} {r.target_hz:7.1f} {r.sent_hz:7.1f} {r.accepted_hz:7.1f} "
              f"{r.latency_p50_ms:7.3f} {r.latency_p99_ms:7.3f} {r.latency_max_ms:7.3f} {r.n:5d}")
    print(f"\n{'autopilot':10} {'event':24} {'takeover after':>15}")
    for autopilot in ("ardupilot", "px4"):
        for event in ("lost", "silent", "spoofed"):
            d = run_detection(autopilot, event)
            print(f"{d.autopilot:10} {d.event:24} {d.detect_s:13.2f} s")


if __name__ == "__main__":
    main()
