"""The command line: user errors are one line (exit 2), bugs keep their traceback, --version, --out."""

from __future__ import annotations

import argparse
import importlib
import logging

import pytest

from visionpos.cli.main import main
from visionpos.config.arena import ConfigError
from visionpos.errors import UsageError


def _fail_with(monkeypatch, exc: BaseException) -> None:
    import visionpos.cli.demo

    def run(args):
        raise exc

    monkeypatch.setattr(visionpos.cli.demo, "run", run)


def test_a_user_error_is_one_line_and_exit_2(monkeypatch, capsys):
    _fail_with(monkeypatch, UsageError("--duration 0: give 0.5 to 3600 seconds"))
    assert main(["demo"]) == 2
    assert capsys.readouterr().err == "visionpos demo: error: --duration 0: give 0.5 to 3600 seconds\n"


def test_config_errors_are_user_errors_until_they_derive_from_visionpos_error(monkeypatch, capsys):
    _fail_with(monkeypatch, ConfigError("arena.yaml", "fusion.x", "unknown setting"))
    assert main(["demo"]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_a_bug_shows_its_traceback(monkeypatch):
    _fail_with(monkeypatch, ValueError("a bug, not the user's input"))
    with pytest.raises(ValueError, match="a bug"):
        main(["demo"])


def test_ctrl_c_exits_130(monkeypatch):
    _fail_with(monkeypatch, KeyboardInterrupt())
    assert main(["demo"]) == 130


def test_argument_problems_in_commands_are_usage_errors(capsys):
    assert main(["demo", "--duration", "0"]) == 2
    assert "give 0.5 to 3600 seconds" in capsys.readouterr().err


def test_version(capsys):
    from visionpos import __version__

    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"visionpos {__version__}"


def test_progress_is_shown_by_default_and_the_rest_stays_quiet():
    # the module, not the function `visionpos.cli.main` that the package re-exports
    cli_main = importlib.import_module("visionpos.cli.main")
    progress = logging.getLogger("visionpos.progress")
    progress.setLevel(logging.NOTSET)
    try:
        cli_main.configure_logging(0)
        assert progress.isEnabledFor(logging.INFO)
        assert not logging.getLogger("visionpos.fusion.pipeline").isEnabledFor(logging.INFO)
    finally:
        progress.setLevel(logging.NOTSET)


def _record_args(*argv: str) -> argparse.Namespace:
    from visionpos.cli import record

    p = argparse.ArgumentParser()
    record.add_arguments(p)
    return p.parse_args(list(argv))


def test_record_writes_to_out_and_still_takes_the_old_positional_file_with_a_warning(capsys):
    from visionpos.cli.record import output_path

    assert output_path(_record_args("--out", "a.mcap", "--config", "thesis")) == "a.mcap"
    assert capsys.readouterr().err == ""
    assert output_path(_record_args("old.mcap", "--config", "thesis")) == "old.mcap"
    assert "deprecated; use `visionpos record --out old.mcap`" in capsys.readouterr().err
    with pytest.raises(UsageError, match="--out"):
        output_path(_record_args("--config", "thesis"))
    with pytest.raises(UsageError, match="once"):
        output_path(_record_args("a.mcap", "--out", "b.mcap", "--config", "thesis"))


def test_tune_checks_the_recording_before_any_trial(tmp_path, capsys, monkeypatch):
    import visionpos.analysis.tune as tune

    monkeypatch.setattr(tune, "run_trial", lambda *a: pytest.fail("a trial ran"))
    assert main(["tune", str(tmp_path / "missing.mcap"), "--grid", "a=1,2"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("visionpos tune: error: ") and "no such recording" in err and err.count("\n") == 1
    not_mcap = tmp_path / "notes.mcap"
    not_mcap.write_text("not a recording")
    assert main(["tune", str(not_mcap), "--grid", "fusion.time_alignment=naive"]) == 2
    assert "not an MCAP file" in capsys.readouterr().err


@pytest.mark.parametrize("argv, interprets", [
    (["demo", "--scenario", "/nonexistent/arena.yaml"], True),
    (["serve", "--config", "/nonexistent/arena.yaml"], False),
    (["sitl", "--scenario", "/nonexistent/arena.yaml"], False),
])
def test_only_the_demo_runs_interpreted_on_a_cold_cache(argv, interprets, monkeypatch):
    """serve and sitl send poses to autopilots: they never start on the interpreted (frame-shedding) fusion."""
    from visionpos.fusion import warmup

    calls = []
    monkeypatch.setattr(warmup, "interpret_while_cold", lambda: calls.append(1) or False)
    assert main(argv) == 2  # the missing arena: a usage error, after the choice
    assert bool(calls) == interprets
