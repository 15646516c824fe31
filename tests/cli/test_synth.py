"""``place-safe synth``: its options and its output file."""

from __future__ import annotations

from place_safe.cli.app import main


def test_a_synth_interrupted_while_writing_leaves_no_frame_file_cut_short(tmp_path, capsys, monkeypatch):
    """Ctrl-C while `synth` wrote its frames left a JSON list without its ']' (`recover` then: "truncated JSON list").
    The frames are drawn before the file is opened, so an interruption while writing now removes the file begun:
    exit 130, one line, no output."""
    from place_safe.sensor.frame import Frame

    to_dict, calls = Frame.to_dict, []

    def interrupted(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return to_dict(self, *args, **kwargs)

    monkeypatch.setattr(Frame, "to_dict", interrupted)
    out = tmp_path / "s.json"
    assert main(["synth", "--frames", "5", "-o", str(out)]) == 130
    assert capsys.readouterr().err.splitlines() == ["place-safe: interrupted"]
    assert len(calls) == 3 and not out.exists()
