"""Plane-capsule contact frames as MuJoCo C computes them, installed into MJX's collision table.

With pyramidal friction cones the orientation of a contact's tangent frame matters: the 4 pyramid edges lie along
its first tangent and the one after. MuJoCo C (`mjc_PlaneCapsule` + `mju_makeFrame`) takes the capsule axis
projected onto the plane as the first tangent whenever the projection is non-zero. MJX 3.17's JAX collider falls
back to a fixed world axis as soon as the projection is shorter than 0.5, i.e. for every capsule steeper than 60
degrees, which is most of a standing UNIMAL's legs; the two then apply different friction pyramids and
trajectories part by centimetres within 0.5 s (measured: 2e-3 m after 9 control steps for a train robot at
MuJoCo's default solver settings, 1e-5 m with this fix).

How it is installed: MJX looks its colliders up in a private, process-wide table (`collision_driver._COLLISION_FUNC`
of the pinned mujoco-mjx) while a step is traced. `install()`, called once when `mjx_morph.sim` is imported, puts
one (plane, capsule) collider there that uses MuJoCo C's frame rule, or MJX's own collider while a step is traced
inside `frames(False)`. So every MJX step traced in this process gets MuJoCo C's frames (the env, the fidelity
check, benchmarks), and an env built with `EnvConfig.c_contact_frames=False` traces its own physics inside
`frames(False)` and gets MJX's frames, whatever other envs exist in the process. Only the tangent frame of
plane-capsule contacts changes. Sphere-plane contacts already agree (MJX's `make_frame` picks (0, 1, 0) like
`mju_makeFrame`). Height-field and box contacts have no MuJoCo C counterpart of the same algorithm in MJX and are
left alone.
"""
from __future__ import annotations

import contextlib
import contextvars
from typing import Iterator

import jax.numpy as jnp
from mujoco.mjx._src import collision_driver, collision_primitive
from mujoco.mjx._src.types import GeomType

_KEY = (GeomType.PLANE, GeomType.CAPSULE)
_MJX = collision_primitive.plane_capsule                 # MJX's own collider (the table's entry before `install`)
_C_FRAMES = contextvars.ContextVar("mjx_morph_c_contact_frames", default=True)


@collision_primitive.collider(ncon=2)
def plane_capsule(plane, cap):
    """Two sphere-plane contacts at the capsule's segment ends, tangent = projected capsule axis."""
    n = plane.mat[:, 2]
    axis = cap.mat[:, 2]
    t = axis - n * jnp.dot(n, axis)
    norm = jnp.linalg.norm(t)
    t = jnp.where(norm > 1e-10, t / jnp.where(norm > 1e-10, norm, 1.0), jnp.array([1.0, 0.0, 0.0]))
    frame = jnp.stack([n, t, jnp.cross(n, t)])
    radius, half = cap.size[0], cap.size[1]
    dists, poss = [], []
    for sign in (1.0, -1.0):
        centre = cap.pos + sign * half * axis
        dist = jnp.dot(centre - plane.pos, n) - radius
        dists.append(dist)
        poss.append(centre - n * (radius + 0.5 * dist))
    return jnp.stack(dists), jnp.stack(poss), jnp.stack([frame, frame])


def _plane_capsule(m, d, key, geom):
    """The installed collider: MuJoCo C's frames, or MJX's inside `frames(False)` (decided while tracing)."""
    return (plane_capsule if _C_FRAMES.get() else _MJX)(m, d, key, geom)


_plane_capsule.ncon = 2
assert _MJX.ncon == plane_capsule.ncon == 2


def install() -> None:
    """Put the plane-capsule collider into MJX's collision table (idempotent; done at import of mjx_morph.sim)."""
    collision_driver._COLLISION_FUNC[_KEY] = _plane_capsule


@contextlib.contextmanager
def frames(c_frames: bool) -> Iterator[None]:
    """Trace the MJX steps inside this block with MuJoCo C's (True) or MJX's own (False) plane-capsule frames."""
    token = _C_FRAMES.set(bool(c_frames))
    try:
        yield
    finally:
        _C_FRAMES.reset(token)
