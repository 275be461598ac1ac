"""mjx_morph: universal morphology control for UNIMAL robots in MuJoCo-MJX and JAX."""
__version__ = "0.1.0"
import contextlib as _contextlib
import io as _io
import re as _re

# MJX's optional Warp backend prints "Failed to import warp: No module named 'warp'" (and the same for mujoco_warp)
# on every import when Warp is not installed. We use MJX's JAX implementation only, so that case is silenced here,
# once, before any module of this package imports MJX; any other output of the import (a broken Warp install, ...)
# is printed as it was.
_WARP_MISSING = _re.compile(r"Failed to import (mujoco_)?warp: No module named '(warp|mujoco_warp)[.\w]*'")
_out = _io.StringIO()
with _contextlib.redirect_stdout(_out):
    from mujoco import mjx as _mjx  # noqa: F401
for _line in _out.getvalue().splitlines():
    if not _WARP_MISSING.fullmatch(_line.strip()):
        print(_line)
