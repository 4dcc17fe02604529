"""The goals table of `visionpos bench`: each goal is judged against what the bench measured."""

from __future__ import annotations

from visionpos.benchmarks import GOALS, GROUPS, BenchResult, Goal
from visionpos.benchmarks.runner import goal_rows, to_markdown


def test_goal_checks_both_directions_and_relative_targets():
    m = {"a": 5.0, "b": 9.0}
    assert Goal("a", "<=", 5.0, "").check(m) == (5.0, 5.0, True)
    assert Goal("a", "<=", 4.9, "").check(m)[2] is False
    assert Goal("a", ">=", 6.0, "").check(m)[2] is False
    assert Goal("a", "<=", None, "", versus="b").check(m) == (5.0, 9.0, True)
    assert Goal("b", "<=", None, "", versus="a").check(m)[2] is False
    assert Goal("missing", "<=", 1.0, "").check(m) == (None, None, None)


def test_markdown_lists_met_and_missed_goals_for_metrics_that_ran():
    res = BenchResult(metrics={"detector_fps_960x640": 1500.0, "replay_speed_x_cpu_thesis": 25.0})
    rows = goal_rows({"x": (res, 1.0)})
    assert [(r[1], r[4]) for r in rows] == [(1500.0, False), (25.0, True)]
    md = to_markdown({"x": (res, 1.0)}, "visionpos bench", False)
    assert "## Goals from the issues" in md and "**no**" in md and "| yes |" in md


def test_every_goal_names_a_metric_prefix_of_a_bench_group():
    for g in GOALS:
        assert g.op in ("<=", ">=")
        assert any(
            g.metric.startswith(p) for p in ("geometry_", "detector_", "fusion_", "bridge_", "calib_", "replay_",
                                              "robustness_", "planner_", "sitl_", "sitl_delay_", "console_",
                                              "backchannel_", "monitor_", "coldstart_", "freshness_")
        )
        assert (g.target is None) == (g.versus is not None)
    assert set(GROUPS) == {"geometry", "detector", "fusion", "bridge", "calibration", "replay", "robustness", "planner",
                           "sitl", "sitl_delay", "console", "backchannel", "camera_monitor", "demo_memory",
                           "coldstart", "freshness"}
