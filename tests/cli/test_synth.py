"""``place-safe synth``: its options and its output file."""

from __future__ import annotations

from place_safe.cli.app import main


def test_a_sensor_seed_for_the_model_generator_is_refused_not_ignored(tmp_path, capsys):
    """`synth --generator model --sensor-seed 3` wrote the frames of the published sensor, the same for every seed,
    without a word: the seed is the independent generator's, as --pulse, --saturation and --crosstalk are, which
    were already refused with the model. Now it is refused with them, exit 2, nothing written."""
    out = tmp_path / "s.json"
    assert main(["synth", "--generator", "model", "--sensor-seed", "3", "--frames", "2", "-o", str(out)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == ["place-safe: error: synth: --sensor-seed, --pulse, --saturation and --crosstalk apply to "
                   "--generator independent only"] and not out.exists()
    assert main(["synth", "--generator", "model", "--frames", "2", "-o", str(out)]) == 0
    assert main(["synth", "--sensor-seed", "3", "--frames", "2", "-o", str(tmp_path / "i.json")]) == 0


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
