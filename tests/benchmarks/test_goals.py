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
                                              "robustness_", "planner_", "sitl_", "sitl_delay_", "sitl_px4_",
                                              "sitl_fleet_", "console_", "backchannel_", "monitor_", "coldstart_",
                                              "freshness_", "scale_")
        )
        assert (g.target is None) == (g.versus is not None)
    assert set(GROUPS) == {"geometry", "detector", "fusion", "bridge", "calibration", "replay", "robustness", "planner",
                           "sitl", "sitl_delay", "sitl_px4", "sitl_px4_delay", "sitl_fleet", "sitl_imu", "console",
                           "backchannel",
                           "camera_monitor", "demo_memory", "coldstart", "freshness", "scale"}


def test_a_partial_run_replaces_its_groups_and_keeps_the_others_with_their_own_run():
    from visionpos.benchmarks.runner import merge_runs, runs_to_markdown

    old = merge_runs({}, {"detector": (BenchResult(metrics={"detector_fps_960x640": 1500.0}), 3.0),
                          "replay": (BenchResult(metrics={"replay_speed_x_cpu_thesis": 25.0}), 4.0)},
                     "visionpos bench", False, when="2026-01-01 00:00 UTC", machine="old box")
    new = merge_runs(old, {"detector": (BenchResult(metrics={"detector_fps_960x640": 2500.0}), 2.0)},
                     "visionpos bench --only detector", False, when="2026-02-02 00:00 UTC", machine="new box")
    assert new["detector"]["metrics"] == {"detector_fps_960x640": 2500.0}
    assert new["replay"] == old["replay"]  # untouched, still labelled with the run that measured it
    assert list(new) == ["detector", "replay"]  # GROUPS order
    md = runs_to_markdown(new)
    # the goals table judges the newest figure; each section names its own run and machine
    assert "| 2500.0 | >= 2000.0 | yes |" in md and "1500" not in md
    assert "by `visionpos bench --only detector`, 2026-02-02 00:00 UTC on new box" in md
    assert "by `visionpos bench`, 2026-01-01 00:00 UTC on old box" in md
    assert "Commands: each group's section names the run it comes from" in md


def test_write_docs_stores_the_runs_beside_the_markdown(tmp_path):
    import json

    from visionpos.benchmarks.runner import write_docs

    md = tmp_path / "benchmarks.md"
    write_docs(md, {"replay": (BenchResult(metrics={"replay_speed_x_cpu_thesis": 25.0}), 4.0)}, "visionpos bench",
               False)
    write_docs(md, {"detector": (BenchResult(metrics={"detector_fps_960x640": 1500.0}), 3.0)},
               "visionpos bench --only detector", False)
    stored = json.loads((tmp_path / "benchmarks.json").read_text())
    assert set(stored) == {"detector", "replay"}
    assert stored["replay"]["metrics"] == {"replay_speed_x_cpu_thesis": 25.0}
    assert "## replay" in md.read_text() and "## detector" in md.read_text()


def test_a_skipped_group_keeps_its_last_figures_and_says_it_was_not_re_run():
    from visionpos.benchmarks.runner import merge_runs, runs_to_markdown

    old = merge_runs({}, {"sitl": (BenchResult(metrics={"sitl_ekf_horizontal_p99_mm": 11.9}), 60.0)},
                     "visionpos bench", False, when="2026-01-01 00:00 UTC", machine="box with SITL")
    skipped = BenchResult(notes=["skipped: no ArduPilot SITL binary"])
    new = merge_runs(old, {"sitl": (skipped, 1.0)}, "visionpos bench", False, when="2026-02-02 00:00 UTC",
                     machine="box without")
    assert new["sitl"]["metrics"] == {"sitl_ekf_horizontal_p99_mm": 11.9}
    assert new["sitl"]["date"] == "2026-01-01 00:00 UTC" and new["sitl"]["machine"] == "box with SITL"
    assert new["sitl"]["notes"] == ["not re-run by `visionpos bench` on 2026-02-02 00:00 UTC: skipped: no ArduPilot "
                                    "SITL binary"]
    assert "not re-run by" in runs_to_markdown(new)
    # with nothing stored, the skip itself is what the docs show
    assert merge_runs({}, {"sitl": (skipped, 1.0)}, "visionpos bench", False)["sitl"]["notes"] == skipped.notes
