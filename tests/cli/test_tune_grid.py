"""`visionpos tune` rejects a grid key that is no setting before it runs any trial."""

from __future__ import annotations

import pytest

from visionpos.cli.main import main


@pytest.fixture(scope="module")
def short_log(tmp_path_factory):
    from visionpos.sim.write import write_recording

    path = tmp_path_factory.mktemp("rec") / "short.mcap"
    write_recording("thesis", path, duration_s=0.5, seed=1)
    return path


@pytest.mark.parametrize("grid, message", [
    ("a=1,2", "not a setting a replay uses"),
    ("fusion.bogus=1,2", "unknown key; `fusion` takes time_alignment"),
    ("fusion.max_residual_px=-1,-2", "must be >= 0.01"),
])
def test_bad_grid_keys_fail_before_any_trial(short_log, grid, message, capsys, monkeypatch):
    import visionpos.analysis.tune as tune

    monkeypatch.setattr(tune, "run_trial", lambda *a: pytest.fail("a trial ran"))
    assert main(["tune", str(short_log), "--grid", grid]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"visionpos tune: error: --grid {grid.split('=')[0]}: ") and message in err
