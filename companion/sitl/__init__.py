"""Closed-loop flights against a real PX4 (SIH) or ArduCopter SITL: ``terraslam sitl``.

The autopilot flies a mission over the simulated city; the camera is rendered from the
autopilot's own simulated truth (``truth``), the real pipeline and bridge run on the SITL's clock,
the SITL's GNSS is switched off with its own command mid-flight, and the report compares our
fixes, the autopilot's estimate and the vehicle's track with that truth (``flight``).

- ``bundle``: find a SITL bundle, start/stop one autopilot with the parameters our output needs.
- ``truth``: the simulator's true state over MAVLink, and the SITL clock derived from it.
- ``vehicle``: the mission client (MAVSDK): wait ready, take off, fly waypoints, GNSS off/on.
- ``flight``: the closed loop and its report.
"""
