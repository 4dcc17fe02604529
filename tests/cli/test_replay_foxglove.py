"""`visionpos replay LOG --foxglove [--out OUT]`: a Foxglove-ready copy of a recording."""

from __future__ import annotations

from visionpos.cli.main import main
from visionpos.recording import RecordingReader


def test_copy_of_a_recording_without_poses(thesis_log, tmp_path, capsys):
    out = tmp_path / "fox.mcap"
    assert main(["replay", str(thesis_log), "--foxglove", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "recorded no poses" in captured.err  # a simulated recording has packets and truth, no outputs
    topics = RecordingReader(out).topics()
    src = RecordingReader(thesis_log).topics()
    assert topics == src  # everything kept; the Foxglove channels `sim` wrote made anew, the same
    assert topics["/foxglove/tf"] >= 1 and topics["/foxglove/arena"] >= 1
    assert sum(n for t, n in topics.items() if t.endswith("/blobs")) > 100
    assert "/foxglove/bodies" not in topics
    assert main(["replay", str(thesis_log), "--foxglove", "--out", str(out)]) == 2  # exists: needs --force
    assert "--force" in capsys.readouterr().err
    assert main(["replay", str(thesis_log), "--foxglove", "--out", str(out), "--force"]) == 0
    assert main(["replay", str(thesis_log), "--foxglove", "--rate", "50"]) == 2
