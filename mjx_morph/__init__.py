"""mjx_morph: universal morphology control for UNIMAL robots in MuJoCo-MJX and JAX."""
__version__ = "0.1.0"
import contextlib as _contextlib
import io as _io
import os as _os
import re as _re

# MJX's optional Warp backend prints "Failed to import warp: No module named 'warp'" (and the same for mujoco_warp)
# on every import when Warp is not installed. We use MJX's JAX implementation only, so that case is silenced here,
# once, before any module of this package imports MJX; any other output of the import (a broken Warp install, ...)
# is printed as it was.
_WARP_MISSING = _re.compile(r"Failed to import (mujoco_)?warp: No module named '(warp|mujoco_warp)[.\w]*'")
#
# `import mujoco` also imports the OpenGL backend named by MUJOCO_GL, and crashes (an AttributeError deep in
# PyOpenGL) when that backend's library is missing, e.g. MUJOCO_GL=osmesa without libOSMesa: every command would
# die at import, training included. This package never uses the context MuJoCo prepares there (`mujoco.GLContext`,
# `mujoco.Renderer`); it makes its own when it renders (`unimal.render.gl_context`, which reports a missing
# backend as `RenderUnavailable`). So MuJoCo is imported with MUJOCO_GL=disable, and the variable is put back
# right after, for `gl_context` and for child processes.
_out = _io.StringIO()
_gl = _os.environ.get("MUJOCO_GL")
_os.environ["MUJOCO_GL"] = "disable"
try:
    with _contextlib.redirect_stdout(_out):
        from mujoco import mjx as _mjx  # noqa: F401
finally:
    if _gl is None:
        del _os.environ["MUJOCO_GL"]
    else:
        _os.environ["MUJOCO_GL"] = _gl
for _line in _out.getvalue().splitlines():
    if not _WARP_MISSING.fullmatch(_line.strip()):
        print(_line)
