"""`visionpos recover`: a recording cut short becomes a clean file mcap's own reader indexes."""

from __future__ import annotations

from mcap.reader import make_reader

from visionpos.cli.main import main
from visionpos.recording import RecordingReader, RecordingWriter


def _cut_recording(tmp_path, n: int = 50, keep: int = 20):
    path = tmp_path / "session.mcap"
    with RecordingWriter(path, {"cameras": []}) as w:
        for i in range(n):
            w.write_packet(i, b"pkt%03d" % i, ("127.0.0.1", 6000))
    data = path.read_bytes()
    path.write_bytes(data[: data.index(b"pkt%03d" % keep) + 2])  # torn inside packet `keep`
    return path


def test_recover_writes_a_clean_file_next_to_the_input(tmp_path, capsys):
    path = _cut_recording(tmp_path)
    before = path.read_bytes()
    assert main(["recover", str(path)]) == 0
    out = tmp_path / "session.recovered.mcap"
    msg = capsys.readouterr().out
    assert "ended early" in msg and str(out) in msg and "20 messages" in msg and "/station/packets 20" in msg
    assert path.read_bytes() == before  # the input is never changed
    with open(out, "rb") as f:
        reader = make_reader(f)
        assert reader.get_summary().statistics.message_count == 20
        assert [m.data for _, _, m in reader.iter_messages()] == [b"pkt%03d" % i for i in range(20)]
    assert RecordingReader(out).complete


def test_recover_refuses_to_overwrite_and_reports_bad_input_in_one_line(tmp_path, capsys):
    path = _cut_recording(tmp_path)
    out = tmp_path / "clean.mcap"
    out.write_bytes(b"keep me")
    assert main(["recover", str(path), "--out", str(out)]) == 2
    assert "exists; pass --force" in capsys.readouterr().err
    assert out.read_bytes() == b"keep me"
    assert main(["recover", str(path), "--out", str(out), "--force"]) == 0
    assert [d for _, d in RecordingReader(out).packets()] == [b"pkt%03d" % i for i in range(20)]
    capsys.readouterr()
    notes = tmp_path / "notes.txt"
    notes.write_text("not a recording")
    assert main(["recover", str(notes), "--out", str(tmp_path / "x.mcap")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "notes.txt" in err and "not an MCAP file" in err
    assert not (tmp_path / "x.mcap").exists() and not (tmp_path / "x.mcap.part").exists()
