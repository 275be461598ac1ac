"""Offscreen pictures of robots with MuJoCo's renderer.

Headless machines need an OpenGL backend: EGL (libEGL, e.g. Debian `libegl1` with Mesa or the NVIDIA driver) or
OSMesa (`libosmesa6`). The backend named by `MUJOCO_GL` is tried first, then egl, then osmesa; if none works,
`RenderUnavailable` says what to install.
"""
from __future__ import annotations

import os
from typing import Sequence

import mujoco
import numpy as np

from .mjcf import to_mjcf
from .morphology import Morphology


class RenderUnavailable(RuntimeError):
    pass


def gl_context(width: int, height: int):
    """A current offscreen GL context (the caller keeps it alive and frees it)."""
    wanted = os.environ.get("MUJOCO_GL", "").lower()
    order = [b for b in (wanted, "egl", "osmesa") if b in ("egl", "osmesa")]
    errors = []
    for backend in dict.fromkeys(order):
        try:
            if backend == "egl":
                from mujoco.egl import GLContext
            else:
                from mujoco.osmesa import GLContext
            ctx = GLContext(width, height)
            ctx.make_current()
            return ctx
        except Exception as e:  # noqa: BLE001 - every backend failure is reported together below
            errors.append(f"{backend}: {type(e).__name__}: {e}")
    raise RenderUnavailable(
        "no OpenGL backend for offscreen rendering (" + "; ".join(errors) + "). Install EGL "
        "(apt-get install libegl1 libgl1, or an NVIDIA driver) and set MUJOCO_GL=egl, or install OSMesa "
        "(apt-get install libosmesa6) and set MUJOCO_GL=osmesa.")


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
