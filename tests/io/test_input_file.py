"""io.input_file: the output-folder check (the input checks are exercised through the frame-file and CLI tests)."""

from __future__ import annotations

from place_safe.io.input_file import output_dir_problem


def test_an_output_folder_is_a_directory_or_a_path_still_to_make(tmp_path):
    assert output_dir_problem(tmp_path) is None
    assert output_dir_problem(tmp_path / "new" / "deeper") is None  # made when written
    f = tmp_path / "file.txt"
    f.write_text("x")
    assert output_dir_problem(f) == "is not a directory"
    assert output_dir_problem(f / "under") == "cannot be a directory (a part of the path is a file)"
