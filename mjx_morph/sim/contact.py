"""Floor-capsule and robot-robot contacts as MuJoCo C makes them (MetaMorph's box floor), installed into MJX's
collision table.

MetaMorph's ft and incline floors are boxes (ft: half-size 100 x 100 x 1 at the origin; incline: 75 x 20 x 1 tilted
-10 degrees about y); ours is the plane through the box's top face. Far from the box's edges (the robots stay there)
MuJoCo C's capsule-box collider, measured on MuJoCo 4.0 over 8000 random capsule poses on both floors (exact to
1e-9 m, `tests/test_sim_fidelity.py` keeps a smaller version of that check), gives:
- candidate points: the two ends of the capsule's segment, end A = centre - half-length * axis tested first, then B;
- if A's end point is inside the box (at or below the face), only A's contact, even when B is deeper; otherwise, if
  B's is inside, only B's; otherwise both ends (each one active when within the margin, as for a plane);
- each contact as a sphere at that end: distance = height of the end above the face - radius, position halfway
  between the sphere's lowest point and the face;
- the frame of `mju_makeFrame(normal)`: normal, then (0, 1, 0) made orthogonal to it, i.e. world-aligned on ft
  and aligned with the slope on incline (the first tangent is the world y axis in both).
With condim 3 the friction pyramid's edges lie along the two tangents, so the frame decides how much traction a
limb gets in each direction: a world-aligned pyramid gives a limb at 45 degrees (UNIMAL limbs grow on a 45 degree
grid) a different forward traction than a pyramid aligned with the limb.

Three rules can be chosen (`EnvConfig.floor_contacts`):
    "box"    the above (MetaMorph's floor, the default);
    "plane"  MuJoCo C's plane-capsule collider: both ends always, first tangent = the capsule axis projected onto
             the plane (`mjc_PlaneCapsule` + `mju_makeFrame`);
    "mjx"    MJX 3.17's own plane-capsule collider: both ends, the projected axis as first tangent unless the
             projection is shorter than 0.5 (capsules steeper than 60 degrees), then a fixed world axis.
Sphere-plane contacts (the torso) already agree with MuJoCo C's sphere-box face contacts (MJX's `make_frame` and
`mju_makeFrame` pick the same tangent). Height-field contacts (csr, obstacle) are MJX's own and are not changed.

Robot-robot contacts: `install()` also replaces MJX's capsule-capsule (limb-limb) and sphere-capsule (torso-limb)
colliders by MuJoCo C's closed forms (`capsule_capsule`, `sphere_capsule`). MJX's project a point on a segment
dividing by |segment|^2 + 1e-6, which puts the closest points ~1e-6 m off along a limb and tilts the normal by
~1e-5 rad; in float64 that was all that still parted MJX's steps from MuJoCo C's with self-collision on, with the
robot-robot contact gap of model.SELF_CONTACT_GAP (session 42, docs/benchmarks.md). For parallel capsules MuJoCo C
makes up to two contacts; the one slot per pair keeps the deepest of them.

Unused slots: `install()` also wraps this collider and MJX's sphere / capsule ones (`never_ranked`) so that, in a
model with a contact budget (`EnvConfig.flat_contact_budget`, `contact_budget`), the contacts of the padded tree's
unused slots, which never carry force, stand at distance INACTIVE instead of their raw (negative: inside the
parent's geom) distance and the budget keeps real contacts first (`never_active_last`, which the height-field
colliders call too).

How it is installed: MJX looks its colliders up in a private, process-wide table (`collision_driver._COLLISION_FUNC`
of the pinned mujoco-mjx) while a step is traced. `install()`, called once when `mjx_morph.sim` is imported, puts
the robot-robot colliders there and one (plane, capsule) collider that applies the rule of the innermost
`floor(rule)` block being traced ("box" outside any block). An env traces its physics inside
`floor(config.floor_contacts)`, so envs with different rules can live in one process.
"""
from __future__ import annotations

import contextlib
import contextvars
from typing import Iterator

import jax.numpy as jnp
from mujoco.mjx._src import collision_driver, collision_primitive, math as mjx_math
from mujoco.mjx._src.types import GeomType

_KEY = (GeomType.PLANE, GeomType.CAPSULE)
_MJX = collision_primitive.plane_capsule                 # MJX's own collider (the table's entry before `install`)
INACTIVE = 1.0e4            # distance of a contact slot that carries no contact (MJX: active iff dist < margin)
NEVER_ACTIVE = -1.0e3       # a pair's margin below this: one of its geoms never touches (model.INERT_MARGIN: the
                            # unused slots of the padded tree)
#: MJX's colliders of the pairs an unused slot can be in on ft / incline (the torso is a sphere, limbs capsules;
#: height-field pairs are hfield_contact's, which ranks unused slots last itself)
_RANKED = ((GeomType.PLANE, GeomType.SPHERE), (GeomType.SPHERE, GeomType.SPHERE), (GeomType.SPHERE, GeomType.CAPSULE),
           (GeomType.CAPSULE, GeomType.CAPSULE))


def _end_contacts(plane, cap):
    """Sphere-plane contacts at the capsule's segment ends A = centre - h axis and B = centre + h axis:
    (heights of the end points above the plane (2,), distances (2,), positions (2, 3))."""
    n = plane.mat[:, 2]
    axis = cap.mat[:, 2]
    radius, half = cap.size[0], cap.size[1]
    ends = jnp.stack([cap.pos - half * axis, cap.pos + half * axis])
    height = (ends - plane.pos) @ n
    dist = height - radius
    pos = ends - n[None, :] * (radius + 0.5 * dist)[:, None]
    return height, dist, pos


@collision_primitive.collider(ncon=2)
def box_face_capsule(plane, cap):
    """MuJoCo C's capsule contacts with the top face of a large box (see the module docstring)."""
    height, dist, pos = _end_contacts(plane, cap)
    a_inside = height[0] <= 0.0
    b_inside = (height[1] <= 0.0) & ~a_inside
    keep = jnp.stack([~b_inside, ~a_inside])
    frame = mjx_math.make_frame(plane.mat[:, 2])
    return jnp.where(keep, dist, INACTIVE), pos, jnp.stack([frame, frame])


@collision_primitive.collider(ncon=2)
def plane_capsule(plane, cap):
    """MuJoCo C's plane-capsule contacts: both segment ends, tangent = the capsule axis projected on the plane."""
    n = plane.mat[:, 2]
    axis = cap.mat[:, 2]
    t = axis - n * jnp.dot(n, axis)
    norm = jnp.linalg.norm(t)
    t = jnp.where(norm > 1e-10, t / jnp.where(norm > 1e-10, norm, 1.0), jnp.array([1.0, 0.0, 0.0]))
    frame = jnp.stack([n, t, jnp.cross(n, t)])
    _, dist, pos = _end_contacts(plane, cap)
    return dist, pos, jnp.stack([frame, frame])


# ---- robot-robot contacts: limb-limb (capsule-capsule) and torso-limb (sphere-capsule) -------------------------

def _parallel_tol(ma, mc):
    """Below this determinant two capsule axes count as parallel: MuJoCo C's mjMINVAL (1e-15) in float64; in float32,
    where the determinant ma mc - mb^2 is lost to rounding below ~eps ma mc, a relative bound (axes within ~1e-3
    rad of parallel)."""
    eps = jnp.finfo(ma.dtype).eps
    return jnp.maximum(1e-15, 8.0 * eps * ma * mc)


@collision_primitive.collider(ncon=1)
def capsule_capsule(cap1, cap2):
    """MuJoCo C's capsule-capsule contact (`mjc_CapsuleCapsule`): the segments' closest points in closed form, the
    first segment's parameter clipped first, then the second's (each recomputed from the other's clipped value),
    and a sphere-sphere contact between them. MJX's own collider divides by |d|^2 + 1e-6 in its segment
    projections, which moves the closest points ~1e-6 m along a limb and tilts the normal ~1e-5 rad (session 42).
    Parallel axes: MuJoCo C makes up to two contacts at the segments' end points; this slot keeps one, the deepest
    of C's four end-point candidates, the first in C's order where ends in the overlap tie (MJX's layout, one
    contact per pair)."""
    a1 = cap1.mat[:, 2] * cap1.size[1]             # half-axes: the segments are pos +- a, parameters in [-1, 1]
    a2 = cap2.mat[:, 2] * cap2.size[1]
    dif = cap1.pos - cap2.pos
    ma, mb, mc = a1 @ a1, -(a1 @ a2), a2 @ a2
    ma, mc = jnp.maximum(ma, jnp.finfo(ma.dtype).tiny), jnp.maximum(mc, jnp.finfo(mc.dtype).tiny)   # no 0 / 0
    u, v = -(a1 @ dif), a2 @ dif
    det = ma * mc - mb * mb
    general = det >= _parallel_tol(ma, mc)
    safe = jnp.where(general, det, 1.0)
    # general case: the lines' closest points, then clip the first parameter, then the second
    x1 = (mc * u - mb * v) / safe
    x2 = (ma * v - mb * u) / safe
    x1c = jnp.clip(x1, -1.0, 1.0)
    x2 = jnp.where(x1c != x1, (v - mb * x1c) / mc, x2)
    x2c = jnp.clip(x2, -1.0, 1.0)
    x1 = jnp.where(x2c != x2, jnp.clip((u - mb * x2c) / ma, -1.0, 1.0), x1c)
    # parallel case: an end of one segment and its projection on the other, for each of the four ends
    ends = jnp.array([1.0, -1.0, 1.0, -1.0], dif.dtype)
    p1 = jnp.concatenate([ends[:2], jnp.clip((u - mb * ends[2:]) / ma, -1.0, 1.0)])
    p2 = jnp.concatenate([jnp.clip((v - mb * ends[:2]) / mc, -1.0, 1.0), ends[2:]])
    gaps = (cap1.pos + p1[:, None] * a1) - (cap2.pos + p2[:, None] * a2)
    sq = jnp.sum(gaps * gaps, axis=1)
    best = jnp.argmax(sq <= sq.min() * (1.0 + 1e-6))      # C's order among the (near-)deepest: overlapping ends tie
    x1 = jnp.where(general, x1, p1[best])
    x2 = jnp.where(general, x2c, p2[best])
    dist, pos, n = collision_primitive._sphere_sphere(cap1.pos + x1 * a1, cap1.size[0],
                                                     cap2.pos + x2 * a2, cap2.size[0])
    return dist, pos, mjx_math.make_frame(n)


@collision_primitive.collider(ncon=1)
def sphere_capsule(sphere, cap):
    """MuJoCo C's sphere-capsule contact (`mjc_SphereCapsule`): the sphere's centre projected on the capsule's
    segment exactly (MJX's own divides by |segment|^2 + 1e-6), then a sphere-sphere contact."""
    a = cap.mat[:, 2] * cap.size[1]
    x = jnp.clip(a @ (sphere.pos - cap.pos) / jnp.maximum(a @ a, jnp.finfo(a.dtype).tiny), -1.0, 1.0)
    dist, pos, n = collision_primitive._sphere_sphere(sphere.pos, sphere.size[0], cap.pos + x * a, cap.size[0])
    return dist, pos, mjx_math.make_frame(n)


#: robot-robot colliders put into MJX's table by `install`, in place of MJX's own
_ROBOT_ROBOT = {(GeomType.CAPSULE, GeomType.CAPSULE): capsule_capsule,
                (GeomType.SPHERE, GeomType.CAPSULE): sphere_capsule}


RULES = {"box": box_face_capsule, "plane": plane_capsule, "mjx": _MJX}
_RULE = contextvars.ContextVar("mjx_morph_floor_contacts", default="box")


def _floor_capsule(m, d, key, geom):
    """The installed collider: the rule of the `floor` block being traced (decided while tracing)."""
    return RULES[_RULE.get()](m, d, key, geom)


_floor_capsule.ncon = 2
assert all(f.ncon == 2 for f in RULES.values())


def never_active_last(m, geom, dist, ncon: int):
    """`dist` (a collider's distances, `ncon` per pair of `geom`) with the contacts of pairs that can never be active
    (a geom of margin model.INERT_MARGIN, an unused slot of the padded tree) moved to distance INACTIVE, where the
    model has a contact budget; unchanged otherwise. They carry no force either way (MJX: active iff dist < margin),
    but an unused slot sits at its parent's origin, inside the parent's geom, so its raw distance is negative (-0.05
    m for a torso-sized overlap): the budget (MJX's `max_contact_points`, which keeps the deepest by raw distance)
    would keep those and drop real contacts. Without a budget the traced program stays as it was."""
    if collision_driver._numeric(m, "max_contact_points") < 0:
        return dist
    never = (m.geom_margin[geom[:, 0]] + m.geom_margin[geom[:, 1]]) < NEVER_ACTIVE
    return jnp.where(jnp.repeat(never, ncon), INACTIVE, dist)


def never_ranked(fn):
    """`fn`, a collider of MJX's table, with its distances passed through `never_active_last`."""
    if getattr(fn, "never_ranked", False):
        return fn

    def ranked(m, d, key, geom):
        dist, pos, frame = fn(m, d, key, geom)
        return never_active_last(m, geom, dist, fn.ncon), pos, frame

    ranked.ncon = fn.ncon
    ranked.never_ranked = True
    return ranked


def install() -> None:
    """Put the floor-capsule collider and MuJoCo C's robot-robot colliders into MJX's collision table, and rank the
    unused slots' contacts of them and of MJX's other sphere colliders last (`never_ranked`) (idempotent; done at
    import of mjx_morph.sim)."""
    table = collision_driver._COLLISION_FUNC
    table[_KEY] = never_ranked(_floor_capsule)
    for key, fn in _ROBOT_ROBOT.items():
        table[key] = never_ranked(fn)
    for key in _RANKED:
        if key in table:
            table[key] = never_ranked(table[key])


def check_rule(rule: str) -> str:
    if rule not in RULES:
        raise ValueError(f"floor_contacts={rule!r}: expected one of {', '.join(RULES)}")
    return rule


@contextlib.contextmanager
def floor(rule: str) -> Iterator[None]:
    """Trace the MJX steps inside this block with floor-capsule contacts of `rule` ("box", "plane" or "mjx")."""
    token = _RULE.set(check_rule(rule))
    try:
        yield
    finally:
        _RULE.reset(token)
