"""io.input_file: the output-folder check and the output's open (the input checks are exercised through the frame-file
and CLI tests)."""

from __future__ import annotations

from place_safe.io.input_file import output_dir_problem, output_open_problem


def test_an_output_folder_is_a_directory_or_a_path_still_to_make(tmp_path):
    assert output_dir_problem(tmp_path) is None
    assert output_dir_problem(tmp_path / "new" / "deeper") is None  # made when written
    f = tmp_path / "file.txt"
    f.write_text("x")
    assert output_dir_problem(f) == "is not a directory"
    assert output_dir_problem(f / "under") == "cannot be a directory (a part of the path is a file)"


def test_an_output_is_opened_before_the_run_and_left_as_it_was(tmp_path):
    kept = tmp_path / "kept.json"
    kept.write_text("mine")
    assert output_open_problem(kept) is None and kept.read_text() == "mine"  # opened to append: unchanged
    new = tmp_path / "new.json"
    assert output_open_problem(new) is None and not new.exists()  # made to try, removed again
    assert output_open_problem("/proc/x.json")  # the system's words: cannot be made there


def test_an_empty_name_is_no_output_folder():
    """``evaluate --out ''`` wrote its plots into the working folder (session 82); an empty output file name was
    already refused."""
    assert output_dir_problem("") == "needs a folder name (it was given an empty one)"
