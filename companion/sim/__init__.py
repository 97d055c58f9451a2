"""Synthetic world, flight, camera, GNSS and autopilot simulator (issue 3).

Live API: ``make_scenario(name, seed, n_frames).steps()`` → SimStep (Frame, TruthPose, GNSS samples,
attitude samples since the previous frame). Scenario names: ``SCENARIOS``.
"""
from companion.sim.scenario import SCENARIOS, Scenario, ScenarioSpec, make_scenario, scenario_spec
from companion.sim.types import AttitudeSample, SimStep, TruthPose

__all__ = ["SCENARIOS", "Scenario", "ScenarioSpec", "make_scenario", "scenario_spec", "AttitudeSample", "SimStep", "TruthPose"]
