"""One source of planner settings: the library's PlannerSettings and the command line's
configuration give the same planner."""

from __future__ import annotations

import dataclasses

import numpy as np

from rrtcolearn import pipeline
from rrtcolearn.config import Config, PlanConfig
from rrtcolearn.planning.rrt import PlannerSettings
from rrtcolearn.systems import make


def test_planner_defaults_are_the_configurations():
    shared = [f.name for f in dataclasses.fields(PlannerSettings)
              if f.name in PlanConfig.model_fields]
    assert len(shared) >= 15
    defaults, plan = PlannerSettings(), PlanConfig()
    for name in shared:
        assert getattr(defaults, name) == getattr(plan, name), name
    assert PlannerSettings.from_config(Config()) == PlannerSettings()


def test_library_settings_resolve_as_the_run_records_them():
    # what a run derives and records in config.toml is what the planner derives itself
    for name in ("pendulum", "cartpole"):
        system = make(name)
        config = pipeline.resolve(Config.model_validate({"system": {"name": name}}), system)
        ours = PlannerSettings().resolved(system)
        for key in ("sigma", "sigma_goal", "control_samples", "extend_distance"):
            assert getattr(ours, key) == getattr(config.plan, key), (name, key)
            assert f"plan.{key}" in config.derived
        assert np.array_equal(ours.metric_scale, system.metric_scale)
        assert ours.connect_reach == ours.data_reach
        # the funnel's extremals as long as the data's longest (the fitted model's)
        assert PlannerSettings(max_duration=7.25).resolved(system).funnel_duration == 7.25


def test_given_values_are_kept():
    system = make("pendulum")
    s = PlannerSettings(sigma=0.3, control_samples=4, extend_distance=0.0,
                        connect_reach=0.7, funnel_duration=2.5).resolved(system)
    assert (s.sigma, s.control_samples, s.extend_distance, s.connect_reach,
            s.funnel_duration) == (0.3, 4, 0.0, 0.7, 2.5)
