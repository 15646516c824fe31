"""Rendering's file names (``place_safe.sim.render``): an image it cannot write is said before anything runs."""

from __future__ import annotations

import pytest

pytest.importorskip("mujoco")

from place_safe.cli.app import main  # noqa: E402
from place_safe.sim.render import image_problem  # noqa: E402


def test_an_image_name_pillow_cannot_write_is_a_problem():
    assert image_problem("scene.png") is None and image_problem("a/b/Scene.JPG") is None
    assert image_problem("scene.txt") == "names no image format Pillow writes (.txt): give a .png file"
    assert image_problem("scene") == "names no image format Pillow writes (no extension): give a .png file"
    # an animation needs a format Pillow writes sequences in: --gif r.jpg rendered, then "KeyError: 'JPEG'" (a review)
    assert image_problem("run.gif", animated=True) is None
    assert image_problem("run.jpg", animated=True) == ("names no animation format Pillow writes (.jpg): give a .gif "
                                                       "file")


@pytest.mark.parametrize("given,said", [(["-o", "scene.txt"], "--output scene.txt"), (["--gif", "rig"], "--gif rig"),
                                        (["--gif", "rig.jpg"], "--gif rig.jpg")])
def test_sim_render_refuses_an_image_name_before_it_renders(given, said, tmp_path, capsys, monkeypatch):
    """`sim render -o x.txt` built and rendered the scene, then ended "invalid input: unknown file extension: .txt"
    (round 14's leftover); `--gif rig` did the same after the PNG. One line naming the option, before the scene is
    built."""
    import place_safe.sim.scene as scene

    def no_scene(*args, **kwargs):
        raise AssertionError("the scene was built")

    monkeypatch.setattr(scene, "build_scene", no_scene)
    monkeypatch.chdir(tmp_path)
    assert main(["sim", "render", *given]) == 2
    flag, name = said.split()
    assert capsys.readouterr().err.splitlines() == [f"place-safe: error: sim render: {said} "
                                                    f"{image_problem(name, animated=flag == '--gif')}"]
