"""Pictures of a scene: offscreen PNGs and GIFs with ``mujoco.Renderer``, and the interactive viewer.

Offscreen rendering needs an OpenGL context; without a display :func:`ensure_gl` selects EGL
(``MUJOCO_GL=egl``) before MuJoCo creates one. Sensor rays can be drawn as line segments from the
``tof_sensor`` site to their hits (one colour per zone; misses drawn to ``miss_length`` metres).
Images are RGB uint8 arrays (H, W, 3).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from place_safe.sim.scene import Scene
from place_safe.exceptions import PlaceSafeError

#: Colour (RGBA) of the rays of each zone 1..9.
ZONE_COLOURS = np.array([[1, 0.2, 0.2, 1], [1, 0.6, 0.1, 1], [1, 1, 0.2, 1], [0.4, 1, 0.2, 1], [0.2, 1, 1, 1],
                         [0.2, 0.5, 1, 1], [0.6, 0.3, 1, 1], [1, 0.3, 0.9, 1], [0.9, 0.9, 0.9, 1]], dtype=np.float32)


def ensure_gl() -> None:
    """Use EGL for offscreen rendering unless a backend is chosen or a display exists.

    MuJoCo picks its OpenGL backend when its rendering module is first imported; if that already
    happened with the default (GLFW, which needs a display), the EGL context class is swapped in.
    """
    if os.environ.get("DISPLAY") or os.environ.get("MUJOCO_GL", "egl").lower() != "egl":
        return
    os.environ["MUJOCO_GL"] = "egl"
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    import sys

    gl = sys.modules.get("mujoco.rendering.classic.gl_context")
    if gl is not None and getattr(gl, "GLContext", None) is not None and "glfw" in gl.GLContext.__module__:
        from mujoco.egl import GLContext

        gl.GLContext = GLContext


ensure_gl()


def _camera(scene: Scene, data: Any, distance: float | None, azimuth: float, elevation: float,
            lookat: np.ndarray | None):
    import mujoco

    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    if lookat is None:
        n, p = scene.table_plane_world(data)
        s = data.site_xpos[scene.sensor_site]
        lookat = 0.5 * (p + s)
    cam.lookat[:] = lookat
    cam.distance = distance if distance is not None else 1.6
    cam.azimuth = azimuth
    cam.elevation = elevation
    return cam


def _draw_rays(renderer: Any, tof: Any, data: Any, stride: int, miss_length: float) -> None:
    import mujoco

    from place_safe.sim.tof import zone_rays_world

    ret = tof.cast(data=data)
    origin, dirs = zone_rays_world(tof, data)
    vscene = renderer.scene
    for z in range(dirs.shape[0]):
        for r in range(0, dirs.shape[1], stride):
            if vscene.ngeom >= vscene.maxgeom:
                return
            length = ret.ranges[z, r] if ret.hit[z, r] else miss_length
            end = origin + dirs[z, r] * length
            g = vscene.geoms[vscene.ngeom]
            mujoco.mjv_initGeom(g, mujoco.mjtGeom.mjGEOM_LINE, np.zeros(3), np.zeros(3), np.zeros(9),
                                ZONE_COLOURS[z])
            mujoco.mjv_connector(g, mujoco.mjtGeom.mjGEOM_LINE, 2.0, origin, end)
            vscene.ngeom += 1


def render_image(scene: Scene, data: Any = None, tof: Any = None, width: int = 640, height: int = 480,
                 distance: float | None = None, azimuth: float = 135.0, elevation: float = -25.0,
                 lookat: np.ndarray | None = None, ray_stride: int = 4, miss_length: float = 0.5,
                 renderer: Any = None) -> np.ndarray:
    """One RGB image (H, W, 3) of the scene; with ``tof`` its rays are drawn (every ``ray_stride``-th)."""
    ensure_gl()
    import mujoco

    d = data if data is not None else scene.make_data()
    own = renderer is None
    r = renderer if renderer is not None else mujoco.Renderer(scene.model, height=height, width=width)
    try:
        opt = mujoco.MjvOption()
        opt.geomgroup[:] = 1
        opt.sitegroup[:] = 1
        r.update_scene(d, camera=_camera(scene, d, distance, azimuth, elevation, lookat), scene_option=opt)
        if tof is not None:
            _draw_rays(r, tof, d, max(1, ray_stride), miss_length)
        return r.render().copy()
    finally:
        if own:
            r.close()


def image_problem(path: str | Path, animated: bool = False) -> str | None:
    """Why :func:`save_png` (or, ``animated``, :func:`save_gif`) cannot write an image named ``path`` (Pillow reads the
    format from its extension), or None. For a check before the run: ``place --sim --render x.txt`` ran the
    placement, then ended "unknown file extension: .txt" with no result file written; ``sim render --gif x.jpg``
    rendered, then ended "KeyError: 'JPEG'" (a format Pillow writes one image of, not a sequence)."""
    from PIL import Image

    Image.init()
    suffix = Path(path).suffix.lower()
    writers = Image.SAVE_ALL if animated else Image.SAVE
    if Image.registered_extensions().get(suffix) not in writers:
        what = "animation" if animated else "image"
        return (f"names no {what} format Pillow writes ({suffix or 'no extension'}): give a "
                f"{'.gif' if animated else '.png'} file")
    return None


def save_png(image: np.ndarray, path: str | Path) -> Path:
    from PIL import Image

    p = Path(path)
    Image.fromarray(np.asarray(image, dtype=np.uint8)).save(p)
    return p


def save_gif(images: list[np.ndarray], path: str | Path, fps: float = 15.0) -> Path:
    from PIL import Image

    p = Path(path)
    frames = [Image.fromarray(np.asarray(im, dtype=np.uint8)) for im in images]
    frames[0].save(p, save_all=True, append_images=frames[1:], duration=int(1000 / fps), loop=0)
    return p


def sweep_frames(scene: Scene, tof: Any, n: int = 20, dz: float = 0.2, **kw: Any) -> list[np.ndarray]:
    """Images of the sensor rig moving down by ``dz`` metres in ``n`` steps (rig scenes)."""
    ensure_gl()
    import mujoco

    d = tof.data
    start = d.mocap_pos[scene.rig_mocap].copy()
    R = d.site_xmat[scene.sensor_site].reshape(3, 3).copy()
    width, height = kw.pop("width", 480), kw.pop("height", 360)
    r = mujoco.Renderer(scene.model, height=height, width=width)
    try:
        out = []
        for s in np.linspace(0.0, 1.0, n):
            scene.set_sensor_pose(d, start - np.array([0, 0, dz * s]), R)
            out.append(render_image(scene, d, tof, renderer=r, **kw))
        return out
    finally:
        r.close()


def view(scene: Scene, data: Any = None) -> None:
    """Open the interactive MuJoCo viewer (needs a display); blocks until closed."""
    if not os.environ.get("DISPLAY") and os.environ.get("MUJOCO_GL") in (None, "egl", "osmesa"):
        raise PlaceSafeError("the interactive viewer needs a display (DISPLAY is not set); use 'sim render' "
                             "to write images instead")
    import mujoco.viewer

    mujoco.viewer.launch(scene.model, data if data is not None else scene.make_data())
