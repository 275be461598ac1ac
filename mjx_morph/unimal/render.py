"""Offscreen pictures of robots with MuJoCo's renderer.

Headless machines need an OpenGL backend: EGL (libEGL, e.g. Debian `libegl1` with Mesa or the NVIDIA driver) or
OSMesa (`libosmesa6`). `MUJOCO_GL=egl` or `MUJOCO_GL=osmesa` uses that backend only; otherwise egl is tried, then
osmesa. PyOpenGL binds one platform per process, at the first backend import, so a backend whose library cannot be
loaded is never imported (`backend_library`): that keeps the next one usable. If none works, `RenderUnavailable`
says what to install, on one line. `check_gl` makes (and frees) a small context: commands call it before any slow
work, so that a missing backend is reported at once, not after loading and compiling.

MuJoCo's own `import mujoco` would import the backend named by MUJOCO_GL, and crash when its library is missing;
`mjx_morph/__init__.py` imports MuJoCo with that step turned off, so the failure comes here, as `RenderUnavailable`.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
from typing import Sequence

import mujoco
import numpy as np

from .mjcf import to_mjcf
from .morphology import Morphology

BACKENDS = ("egl", "osmesa")
# the shared library PyOpenGL loads for each backend, and the file names it tries (the versioned ones are what a
# distribution installs without its -dev package)
BACKEND_LIBRARIES = {"egl": ("EGL", ("libEGL.so", "libEGL.so.1")),
                     "osmesa": ("OSMesa", ("libOSMesa.so", "libOSMesa.so.8", "libOSMesa.so.6"))}
INSTALL = ("Install EGL (apt-get install libegl1 libgl1, or an NVIDIA driver) and set MUJOCO_GL=egl, or install "
           "OSMesa (apt-get install libosmesa6) and set MUJOCO_GL=osmesa")


class RenderUnavailable(RuntimeError):
    pass


def backend_library(backend: str) -> str | None:
    """The file name under which the shared library of `backend` ("egl" or "osmesa") loads, None if it does not."""
    name, files = BACKEND_LIBRARIES[backend]
    found = ctypes.util.find_library(name)
    for f in ((found,) if found else ()) + files:
        try:
            ctypes.CDLL(f)
        except OSError:
            continue
        return f
    return None


def _one_line(e: BaseException) -> str:
    return " ".join(f"{type(e).__name__}: {e}".split())


def gl_context(width: int, height: int):
    """A current offscreen GL context (the caller keeps it alive and frees it); `RenderUnavailable` if none."""
    wanted = os.environ.get("MUJOCO_GL", "").strip().lower()
    order = (wanted,) if wanted in BACKENDS else BACKENDS
    errors = []
    for backend in order:
        if backend_library(backend) is None:
            name, files = BACKEND_LIBRARIES[backend]
            errors.append(f"{backend}: lib{name} is not installed ({', '.join(files)} cannot be loaded)")
            continue
        try:
            if backend == "egl":
                from mujoco.egl import GLContext       # imported only now: it binds PyOpenGL to EGL
            else:
                from mujoco.osmesa import GLContext    # imported only now: it binds PyOpenGL to OSMesa
            ctx = GLContext(width, height)
            ctx.make_current()
            return ctx
        except Exception as e:  # noqa: BLE001 - every backend failure is reported together below
            errors.append(f"{backend}: {_one_line(e)}")
    chosen = f"MUJOCO_GL={wanted}: only that backend is tried; " if wanted in BACKENDS else ""
    raise RenderUnavailable(f"no OpenGL backend for offscreen rendering ({chosen}{'; '.join(errors)}). {INSTALL}.")


def check_gl() -> None:
    """Raise `RenderUnavailable` now if no OpenGL context can be made (a 16 x 16 one is made and freed)."""
    gl_context(16, 16).free()


class OffscreenRenderer:
    """Renders MjData of one model into RGB arrays with an explicit GL context (no window, no import-order
    dependence on MUJOCO_GL)."""

    def __init__(self, model: mujoco.MjModel, width: int = 320, height: int = 240):
        self.model, self.width, self.height = model, width, height
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, width)
        model.vis.global_.offheight = max(model.vis.global_.offheight, height)
        self.ctx = gl_context(width, height)
        self.scene = mujoco.MjvScene(model, maxgeom=2000)
        self.option = mujoco.MjvOption()
        self.con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self.con)
        self.camera = mujoco.MjvCamera()
        self.viewport = mujoco.MjrRect(0, 0, width, height)

    def render(self, data: mujoco.MjData, *, lookat=None, distance=2.0, azimuth=135.0, elevation=-20.0) -> np.ndarray:
        cam = self.camera
        cam.type = mujoco.mjtCamera.mjCAMERA_FREE
        cam.lookat[:] = data.xpos[1] if lookat is None else lookat
        cam.distance, cam.azimuth, cam.elevation = distance, azimuth, elevation
        self.ctx.make_current()
        mujoco.mjv_updateScene(self.model, data, self.option, None, cam, mujoco.mjtCatBit.mjCAT_ALL, self.scene)
        mujoco.mjr_render(self.viewport, self.scene, self.con)
        rgb = np.empty((self.height, self.width, 3), dtype=np.uint8)
        mujoco.mjr_readPixels(rgb, None, self.viewport, self.con)
        return np.flipud(rgb)

    def close(self) -> None:
        self.con.free()
        self.ctx.free()


_LOOK = """
  <visual><headlight ambient=".5 .5 .5" diffuse=".7 .7 .7"/></visual>
  <asset>
    <texture name="grid" type="2d" builtin="checker" rgb1=".75 .8 .85" rgb2=".6 .65 .7" width="256" height="256"/>
    <material name="grid" texture="grid" texrepeat="8 8"/>
  </asset>
"""


def _scene_xml(m: Morphology) -> str:
    xml = to_mjcf(m, floor=True)
    xml = xml.replace('type="plane"', 'type="plane" material="grid"', 1)
    xml = xml.replace('friction="0.7 0.1 0.1"/>', 'friction="0.7 0.1 0.1" rgba=".85 .5 .25 1"/>', 1)
    return xml.replace("</mujoco>", _LOOK + "</mujoco>")


def render_robots(robots: Sequence[Morphology], size: int = 240) -> list[np.ndarray]:
    """One picture per robot standing at its rest pose on a floor."""
    images = []
    renderer = None
    try:
        for m in robots:
            model = mujoco.MjModel.from_xml_string(_scene_xml(m))
            data = mujoco.MjData(model)
            mujoco.mj_forward(model, data)
            if renderer is not None:
                renderer.close()
            renderer = OffscreenRenderer(model, size, size)
            extent = float(np.abs(m.rest_positions() - [0, 0, m.height]).max(initial=0.3)) + 0.5
            images.append(renderer.render(data, lookat=[0, 0, m.height * 0.6], distance=2.2 * extent + 0.6))
    finally:
        if renderer is not None:
            renderer.close()
    return images
