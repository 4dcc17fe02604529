"""The cold start benchmark's logic (not a cold start itself: that is minutes of CPU)."""

import threading
import time

from visionpos.benchmarks import coldstart


def test_first_pose_is_read_from_the_demo_process_line():
    err = "visionpos demo: 4 simulated stations\nVISIONPOS_FIRST_POSE 1012.5 7.25\nVISIONPOS_FIRST_POSE 1013.0 8.0\n"
    assert coldstart.first_pose(err, 1000.0) == (12.5, 7.25)  # the first one
    assert coldstart.first_pose("no pose here\n", 1000.0) == (None, None)


def test_the_driver_reports_the_first_non_empty_publish(monkeypatch, capsys):
    """The driver's patch of the demo's Collector prints one line, at the first publish with states."""
    import importlib

    from visionpos.app import demo

    cli_main = importlib.import_module("visionpos.cli.main")

    monkeypatch.setattr(demo.Collector, "publish", demo.Collector.publish)  # restored after the test
    monkeypatch.setattr(cli_main, "main", lambda argv: 0)
    monkeypatch.setattr("sys.argv", ["-c", "demo"])
    try:
        exec(compile(coldstart._DRIVER, "<driver>", "exec"), {"__name__": "__driver__"})
    except SystemExit as e:
        assert e.code == 0
    c = demo.Collector(["quad"])
    c.publish([])
    assert coldstart.FIRST_POSE_TAG not in capsys.readouterr().err
    from types import SimpleNamespace

    c.publish([SimpleNamespace(name="quad")])
    c.publish([SimpleNamespace(name="quad")])
    err = capsys.readouterr().err
    assert err.count(coldstart.FIRST_POSE_TAG) == 1
    assert coldstart.first_pose(err, 0.0)[0] > 0
    assert "--no-console" in coldstart.demo_command(5.0) and "demo" in coldstart.demo_command(5.0)


def test_wait_for_record(tmp_path):
    from visionpos.fusion.warmup import _hot_record

    # the first stage's record (one kernel compiled) does not say the cache is complete
    _hot_record(tmp_path / "fusion-warm-up-abc.pickle").write_bytes(b"")
    assert coldstart.wait_for_record(str(tmp_path), 0.01) is None
    threading.Timer(0.2, lambda: (tmp_path / "fusion-warm-up-abc.pickle").write_bytes(b"")).start()
    t0 = time.monotonic()
    assert coldstart.wait_for_record(str(tmp_path), 10.0) is not None
    assert time.monotonic() - t0 < 5.0


def test_run_reports_cold_and_warm(monkeypatch):
    runs = iter([{"first_pose_s": 14.0, "cpu_s": 9.0, "wall_s": 20.0, "load": 1.5},
                 {"first_pose_s": 4.0, "cpu_s": 3.5, "wall_s": 10.0, "load": 1.0}])
    caches = []
    monkeypatch.setattr(coldstart, "run_once", lambda cache, d: (caches.append(cache), next(runs))[1])
    monkeypatch.setattr(coldstart, "wait_for_record", lambda cache, timeout: 42.0)
    res = coldstart.run(quick=True)
    assert caches[0] == caches[1]  # the warm run uses the cache the cold run filled
    assert res.metrics == {"coldstart_first_pose_s": 14.0, "coldstart_cpu_s": 9.0, "warmstart_first_pose_s": 4.0,
                           "warmstart_cpu_s": 3.5, "coldstart_compile_after_demo_s": 42.0}
    (text,) = res.tables.values()
    assert "| 14.0 | 9.0 | 1.50 |" in text and "| 4.0 | 3.5 | 1.00 |" in text and "42.0 s" in text


def test_run_without_a_finished_compilation_has_no_warm_run(monkeypatch):
    monkeypatch.setattr(coldstart, "run_once", lambda cache, d: {"first_pose_s": 14.0, "cpu_s": 9.0, "wall_s": 1.0,
                                                                 "load": 1.0})
    monkeypatch.setattr(coldstart, "wait_for_record", lambda cache, timeout: None)
    res = coldstart.run(quick=True)
    assert "warmstart_first_pose_s" not in res.metrics and res.notes
