"""Height-field contacts for MJX as MuJoCo C makes them for spheres and capsules, installed into MJX's collision table.

MuJoCo C (MuJoCo 4.0: engine_collision_convex.c `mjc_ConvexHField`, with native CCD, the default, in
engine_collision_gjk.c `mjc_ccd`) collides a convex geom with a height field prism by prism:
- the geom's axis-aligned box in the height field's frame (from its support function: a capsule's is centre
  +- (radius + half-length |axis_i|)) picks the cells: columns cmin = floor((xmin + sx) / (2 sx) (ncol - 1)) to
  cmax = ceil((xmax + sx) / (2 sx) (ncol - 1)) clipped to [0, ncol - 1], the same for rows; cells (c, r) with
  cmin <= c < cmax and rmin <= r < rmax, row by row (r outer, then c);
- each cell is two triangular prisms, vertex (c, r) at (c dx - sx, r dy - sy, data[r ncol + c] sz): first
  (c, r+1), (c, r), (c+1, r+1), then (c, r), (c+1, r+1), (c+1, r) (the diagonal from (c, r) to (c+1, r+1)); a prism
  is its top triangle over the bottom plane z = -base (the height field's fourth size);
- a prism is skipped when its three top vertices all lie below the geom's lowest point; otherwise `mjc_ccd` makes
  at most one contact with it (nconmax 1), only when they penetrate (distance < 0);
- at most mjMAXCONPAIR = 50 contacts per geom pair (the first 50 in the order above).
For a sphere or a capsule, `mjc_ccd` shrinks the geom to its centre point or its segment (the core) and runs GJK
between two polytopes: when their distance d exceeds the CCD tolerance (1e-6 m) the contact is their closest points
x1 (prism) and x2 (core), normal n = (x2 - x1) / d (from the height field to the geom), distance d - r, position
halfway between x1 and the geom's surface point x2 - r n. Only when the core itself touches the prism (penetration
deeper than the radius) does it run EPA on the full geom: distance minus the penetration depth along the direction
of least penetration, EPA's witness points. The frame is `mju_makeFrame(normal)` (first tangent (0, 1, 0), or
(0, 0, 1) when the normal's |y| is 0.5 or more, made orthogonal to the normal), as MJX's `math.make_frame`.

MJX 3.17 (`collision_convex.hfield_sphere` / `hfield_capsule` / `_hfield_collision`) collides the geom with every
prism of a fixed window of cells around its bounding sphere (`geom_rbound_hfield`, clipped into the field by
repeating border cells) through its own sphere / capsule-convex colliders, keeps only the candidates within 1 mm of
the deepest, and of those 4 "manifold points" per pair (`_manifold_points`), with the prism's top normal where a
normal points downwards: fewer contacts than MuJoCo C as soon as a geom touches more than 4 prisms, at other points.

Here (`hfield_geom`): MuJoCo C's contacts computed exactly, vectorised over the prisms of MJX's window (which holds
MuJoCo C's cells; the others are masked): the core's closest features against each prism (endpoint-face and
segment-edge pairs) and, for the deep case, the depth by separating axes (prism face normals and segment x edge
directions) with the witness on the deepest core point. Measured against MuJoCo 4.0 on random poses over random,
flat and stepped fields (tests/test_sim_hfield_contact.py keeps a small version): same number of contacts in the
same order, and in float64 distances, points and frames equal to 1e-12 where GJK decides; in the deep case the depth
to EPA's tolerance (< 1e-6 m), the normal to 2e-5 and the point to 3.5e-4 m (EPA stops at 1e-6 m of depth on a
curved surface, which leaves the point undetermined by ~sqrt(2 r 1e-6)); in float32 (MJX) ~1e-6 m, up to 1e-5 m
where two features of a prism are equally close to float32 precision.

Cost (`hfield_group`, `candidates` > 0, the env's default 96): MJX calls a collider once per group of pairs of one
window size (the train set: 20 capsules with 7 x 7 cells, 6 with 6 x 6, the torso sphere with 4 x 4: 2,424 prisms
per env). Most geoms are in the air, so a cheap lower bound (`_bound`: the core's lowest point over the prism's
cell, about 30 flops) picks the `candidates` prisms of the group that can touch, and only those get the exact
test; the contacts are then placed in their pairs' slots as `hfield_geom` places them. Over 150 control steps of
random actions of 64 envs of the train set on csr, the groups had at most 18 / 72 / 24 prisms that pass the bound
(mean 0.2 / 6.3 / 0.1), so 96 drops none there; if a group has more, those of highest bound are dropped.

MJX's contact arrays have a fixed size: a collider declares its contacts per pair (`ncon`), MJX allocates
ncon x (number of pairs) rows per function key (`collision_driver.make_condim`, called by `make_data`) and repeats
each pair's contact parameters ncon times (`collision_driver.collision`). This collider declares `per_geom` (32
by default) and returns MuJoCo C's contacts first, in MuJoCo C's order (the `per_geom` deepest if there are more),
then unused slots at distance INACTIVE (MJX: active iff distance < margin). Geoms that can never touch (the unused
slots' margin -1e4, model.INERT_MARGIN) get INACTIVE too where the model has an env-wide contact budget (MJX's
`max_contact_points`, `padding.SolverOptions.contact_budget`: it keeps the deepest contacts of all pairs), so that
it never keeps them (`contact.never_active_last`).

How it is installed (as contact.py's floor collider): `install()`, called once when `mjx_morph.sim` is imported,
puts one entry for (height field, sphere) and one for (height field, capsule) into MJX's private collision table
(`collision_driver._COLLISION_FUNC`). Each applies the rule of the innermost `rule(name, per_geom)` block being
traced: "mujoco" (the above, the default outside any block) or "mjx" (MJX's own, 4 per pair). The rule decides
the size of MJX's contact arrays, so `make_data` and every traced step of one model must run under the same rule
(an env does both inside `UnimalEnv.physics()`).
"""
from __future__ import annotations

import contextlib
import contextvars
import functools
from typing import Iterator, Tuple

import jax
import jax.numpy as jnp
from mujoco.mjx._src import collision_convex, collision_driver, math as mjx_math, mesh
from mujoco.mjx._src.types import GeomType

from .contact import INACTIVE, never_active_last

CCD_TOLERANCE = 1.0e-6      # mjOption.ccd_tolerance (default): below this core distance MuJoCo C runs EPA
_BIG = 1.0e10


def _dot(a, b):
    return jnp.sum(a * b, axis=-1)


def _safe(x):
    return jnp.where(x == 0.0, 1.0, x)


def seg_seg(p1, q1, p2, q2):
    """Closest points of segments [p1, q1] and [p2, q2] (Ericson, Real-Time Collision Detection 5.1.9), batched
    over leading axes; a segment may be a point. Returns (c1, c2)."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e, f = _dot(d1, d1), _dot(d2, d2), _dot(d2, r)
    c, b = _dot(d1, r), _dot(d1, d2)
    tiny = 1e-20
    a0, e0 = a <= tiny, e <= tiny
    # a e - b^2 and b f - c e through cross products (Binet-Cauchy): no cancellation for nearly parallel segments
    n = jnp.cross(d1, d2)
    denom = _dot(n, n)
    num = _dot(n, jnp.cross(d2, r))
    s = jnp.where(denom > 1e-12 * a * e, jnp.clip(num / _safe(denom), 0.0, 1.0), 0.0)
    t = (b * s + f) / _safe(e)
    s = jnp.where(t < 0.0, jnp.clip(-c / _safe(a), 0.0, 1.0), jnp.where(t > 1.0, jnp.clip((b - c) / _safe(a),
                                                                                         0.0, 1.0), s))
    t = jnp.clip(t, 0.0, 1.0)
    # degenerate segments
    s = jnp.where(a0, 0.0, jnp.where(e0, jnp.clip(-c / _safe(a), 0.0, 1.0), s))
    t = jnp.where(a0, jnp.where(e0, 0.0, jnp.clip(f / _safe(e), 0.0, 1.0)), jnp.where(e0, 0.0, t))
    return p1 + s[..., None] * d1, p2 + t[..., None] * d2


def _normalize(v):
    n = jnp.linalg.norm(v, axis=-1, keepdims=True)
    return v / jnp.where(n > 0.0, n, 1.0), n[..., 0]


def prism_contact(top, zbot, a, b, radius):
    """MuJoCo C's contact of a sphere-swept segment [a, b] (a == b: a sphere) of `radius` with one prism: the top
    triangle `top` (3, 3) over the plane z = zbot (all in the height field's frame).

    Returns (dist, pos (3,), normal (3,)); dist >= 0 means no contact (MuJoCo C makes one iff dist < 0)."""
    bot = top.at[:, 2].set(zbot)
    verts = jnp.concatenate([bot, top])                                   # (6, 3)
    centre = jnp.mean(verts, axis=0)

    # faces: outward unit normals and a point on each (top, bottom, 3 sides)
    n_top, _ = _normalize(jnp.cross(top[1] - top[0], top[2] - top[0]))
    n_top = n_top * jnp.sign(n_top[2])
    e_xy = jnp.roll(top, -1, axis=0) - top                                # edge j: vertex j -> j+1
    n_side, _ = _normalize(jnp.stack([e_xy[:, 1], -e_xy[:, 0], jnp.zeros(3)], axis=-1))
    away = _dot(top - centre, n_side)                                     # outward iff the centre is behind
    n_side = n_side * jnp.where(away >= 0.0, 1.0, -1.0)[:, None]
    normals = jnp.concatenate([n_top[None], jnp.array([[0.0, 0.0, -1.0]]), n_side])       # (5, 3)
    face_pt = jnp.concatenate([top[:1], bot[:1], top])                                   # a point on each face

    # the 9 edges: top j -> j+1, bottom j -> j+1, vertical j
    e0 = jnp.concatenate([top, bot, bot])
    e1 = jnp.concatenate([jnp.roll(top, -1, 0), jnp.roll(bot, -1, 0), top])

    # separating axes: face normals and segment direction x edge directions
    d = b - a
    edir = e1 - e0
    cross, cn = _normalize(jnp.cross(d[None], edir))
    ok_cross = cn > 1e-9 * jnp.linalg.norm(d) * jnp.linalg.norm(edir, axis=-1)
    axes = jnp.concatenate([normals, cross])                                           # (14, 3)
    ok = jnp.concatenate([jnp.ones(5, bool), ok_cross])
    pv = verts @ axes.T                                                                # (6, 14)
    ps = jnp.stack([a, b]) @ axes.T                                                    # (2, 14)
    up = pv.max(0) - ps.min(0)          # overlap when the geom moves along +axis
    down = ps.max(0) - pv.min(0)        # ... along -axis
    overlap = jnp.where(ok, jnp.minimum(up, down), _BIG)
    k = jnp.argmin(overlap)
    sat_depth = jnp.maximum(overlap[k], 0.0)                              # the core's penetration (deep case)
    n_deep = axes[k] * jnp.where(up[k] <= down[k], 1.0, -1.0)

    # shallow: closest features. (1) core endpoints against face interiors (sides split in two triangles)
    tri = jnp.stack([top,                                                            # top
                     bot,                                                            # bottom
                     jnp.stack([bot[0], bot[1], top[1]]), jnp.stack([bot[0], top[1], top[0]]),
                     jnp.stack([bot[1], bot[2], top[2]]), jnp.stack([bot[1], top[2], top[1]]),
                     jnp.stack([bot[2], bot[0], top[0]]), jnp.stack([bot[2], top[0], top[2]])])   # (8, 3, 3)
    tri_n = normals[jnp.array([0, 1, 2, 2, 3, 3, 4, 4])]                                    # (8, 3)
    pts = jnp.stack([a, b])                                                                  # (2, 3)
    s = _dot(pts[:, None] - tri[None, :, 0], tri_n[None])                                  # (2, 8)
    q = pts[:, None] - s[..., None] * tri_n[None]                                           # (2, 8, 3)
    w = [_dot(jnp.cross(tri[None, :, (j + 1) % 3] - tri[None, :, j], q - tri[None, :, j]), tri_n[None])
         for j in range(3)]
    inside = ((w[0] >= 0) & (w[1] >= 0) & (w[2] >= 0)) | ((w[0] <= 0) & (w[1] <= 0) & (w[2] <= 0))
    face_d = jnp.where(inside & (s >= 0.0), s, _BIG).reshape(-1)                            # (16,)
    face_core = jnp.repeat(pts, 8, axis=0)
    face_prism = q.reshape(-1, 3)
    # (2) the core segment against the 9 prism edges
    c_core, c_prism = seg_seg(a[None], b[None], e0, e1)                                      # (9, 3) each
    edge_d = jnp.linalg.norm(c_core - c_prism, axis=-1)
    all_d = jnp.concatenate([face_d, edge_d])
    j = jnp.argmin(all_d)
    core = jnp.concatenate([face_core, c_core])[j]
    prism = jnp.concatenate([face_prism, c_prism])[j]
    dcore = all_d[j]
    n_sh = (core - prism) / jnp.where(dcore > 0.0, dcore, 1.0)
    dist_sh = dcore - radius
    pos_sh = prism + 0.5 * dist_sh * n_sh

    # does the core enter the prism? (clipped against the 5 face planes; exact, unlike the separating axes, which
    # leave out the cross axes of nearly parallel directions)
    fa, fb = _dot(a - face_pt, normals), _dot(b - face_pt, normals)                        # (5,) each
    t_cut = fa / _safe(fa - fb)
    t_in = jnp.max(jnp.where((fa > 0.0) & (fb <= 0.0), t_cut, 0.0))
    t_out = jnp.min(jnp.where((fa <= 0.0) & (fb > 0.0), t_cut, 1.0))
    enters = ~jnp.any((fa > 0.0) & (fb > 0.0)) & (t_in <= t_out)

    # deep (the core touches the prism): depth along the axis of least penetration, plus the radius
    deep = enters | (dcore <= CCD_TOLERANCE)
    ends = pts @ n_deep
    is_face = k < 5
    end_pt = jnp.where(ends[0] <= ends[1], a, b)
    # edge axes: the edge of that direction on the prism's side facing the geom (one of 3 for vertical edges)
    ke = jnp.where(k >= 11, 6 + jnp.argmax(_dot(top, n_deep)), k - 5)
    edge_pt = seg_seg(a, b, e0[ke], e1[ke])[0]
    core_pt = jnp.where(is_face, end_pt, edge_pt)
    depth = sat_depth + radius
    pos_dp = core_pt - radius * n_deep + 0.5 * depth * n_deep
    dist = jnp.where(deep, -depth, dist_sh)
    pos = jnp.where(deep, pos_dp, pos_sh)
    normal = jnp.where(deep, n_deep, n_sh)
    return dist, pos, normal


def _window(h, pos, mat, radius, half, subgrid: Tuple[int, int]):
    """The prisms of MJX's cell window of `subgrid` = (columns, rows) cells around a capsule (half-length `half`;
    0: a sphere) of `radius` at `pos`, `mat` (world) over the height field `h` (MJX's HFieldInfo: pos, mat, size,
    nrow, ncol, data (ncol, nrow)), in MuJoCo C's order. Returns, in the height field's frame:
    tops (Q, 3, 3)   each prism's top triangle (Q = 2 x cells; the bottom plane is z = -h.size[3])
    valid (Q,)       MuJoCo C would test the prism (its cell window, its early exits, the prism height test)
    a, b (3,)        the ends of the geom's core (a == b for a sphere)
    bound (Q,)       a lower bound on the prism's contact distance along z: contact (distance < 0) implies
                     bound < 0 (see `_bound`)."""
    sx, sy, sz = h.size[0], h.size[1], h.size[2]
    nrow, ncol = h.nrow, h.ncol
    p = h.mat.T @ (pos - h.pos)                       # geom in the height field's frame
    axis = h.mat.T @ mat[:, 2]
    ext = radius + half * jnp.abs(axis)               # half extents of the axis-aligned box
    lo, hi = p - ext, p + ext
    # MuJoCo C's sub-grid: cells cmin <= c < cmax, rmin <= r < rmax
    cmin = jnp.maximum(jnp.floor((lo[0] + sx) / (2.0 * sx) * (ncol - 1)), 0).astype(jnp.int32)
    cmax = jnp.minimum(jnp.ceil((hi[0] + sx) / (2.0 * sx) * (ncol - 1)), ncol - 1).astype(jnp.int32)
    rmin = jnp.maximum(jnp.floor((lo[1] + sy) / (2.0 * sy) * (nrow - 1)), 0).astype(jnp.int32)
    rmax = jnp.minimum(jnp.ceil((hi[1] + sy) / (2.0 * sy) * (nrow - 1)), nrow - 1).astype(jnp.int32)
    # MuJoCo C's early exits: the box outside the height field's box
    outside = ((lo[0] > sx) | (hi[0] < -sx) | (lo[1] > sy) | (hi[1] < -sy) | (lo[2] > sz) | (hi[2] < -h.size[3]))
    dx = 2.0 * sx / (ncol - 1)
    dy = 2.0 * sy / (nrow - 1)

    nc, nr = subgrid
    r = rmin + jnp.repeat(jnp.arange(nr), nc)         # row-major: r outer, c inner
    c = cmin + jnp.tile(jnp.arange(nc), nr)
    valid = (r < rmax) & (c < cmax) & ~outside
    r0, c0 = jnp.clip(r, 0, nrow - 2), jnp.clip(c, 0, ncol - 2)

    def vert(ci, ri):
        return jnp.stack([dx * ci - sx, dy * ri - sy, h.data[ci, ri] * sz], axis=-1)

    v00, v01 = vert(c0, r0), vert(c0, r0 + 1)         # v<dc><dr>
    v10, v11 = vert(c0 + 1, r0), vert(c0 + 1, r0 + 1)
    tops = jnp.stack([jnp.stack([v01, v00, v11], axis=1),        # (cells, 2, 3, 3): MuJoCo C's two prisms
                      jnp.stack([v00, v11, v10], axis=1)], axis=1).reshape(-1, 3, 3)
    valid = jnp.repeat(valid, 2)
    zmin = p[2] - ext[2]
    valid &= ~jnp.all(tops[:, :, 2] < zmin, axis=1)   # prism height test
    a, b = p - half * axis, p + half * axis
    cell_lo = jnp.repeat(v00[:, :2], 2, axis=0)                   # each prism's cell, (Q, 2)
    bound = _bound(a, b, radius, cell_lo, jnp.array([dx, dy]), jnp.max(tops[:, :, 2], axis=1))
    return tops, valid, a, b, bound


BOUND_SLACK = 1.0e-4        # float32 headroom (m) of the candidate test `_bound < BOUND_SLACK`


def _bound(a, b, radius, cell_lo, cell_size, ztop):
    """A lower bound on the contact distance of the core [a, b] (radius `radius`) with prisms whose xy lies in the
    cells [cell_lo, cell_lo + cell_size] and whose top is at most `ztop`: a core point within `radius` of such a
    prism lies over the cell widened by `radius` and at most `radius` above `ztop`, so with z_low the core's lowest
    point over the widened cell, contact implies z_low - radius - ztop < 0. Prisms the core never passes over get
    +_BIG. Batched over the leading axis of `cell_lo` and `ztop`; about 30 flops a prism, against the exact test's
    thousands."""
    d = b - a
    lo = cell_lo - radius - BOUND_SLACK
    hi = cell_lo + cell_size + radius + BOUND_SLACK
    t0 = (lo - a[:2]) / _safe(d[:2])
    t1 = (hi - a[:2]) / _safe(d[:2])
    flat = jnp.abs(d[:2]) < 1e-12                                     # parallel to the slab: inside or never
    inside = (a[:2] >= lo) & (a[:2] <= hi)
    t_lo = jnp.where(flat, jnp.where(inside, 0.0, _BIG), jnp.minimum(t0, t1))
    t_hi = jnp.where(flat, jnp.where(inside, 1.0, -_BIG), jnp.maximum(t0, t1))
    t_in = jnp.maximum(jnp.max(t_lo, axis=-1), 0.0)
    t_out = jnp.minimum(jnp.min(t_hi, axis=-1), 1.0)
    z_low = a[2] + jnp.minimum(t_in * d[2], t_out * d[2])          # z is linear along the core
    return jnp.where(t_in <= t_out, z_low - radius - ztop, _BIG)


def hfield_geom(h, pos, mat, radius, half, subgrid: Tuple[int, int], ncon: int):
    """MuJoCo C's contacts of a capsule (half-length `half`; 0: a sphere) of `radius` at `pos`, `mat` (world) with
    the height field `h` (MJX's HFieldInfo: pos, mat, size, nrow, ncol, data (ncol, nrow)), on the cells of a
    window of `subgrid` = (columns, rows) cells (MJX's, from the geom's bounding radius: covers MuJoCo C's cells),
    every prism of the window tested exactly.

    Returns (dist (ncon,), pos (ncon, 3), frame (ncon, 3, 3)) in world coordinates, MuJoCo C's contacts first in
    its order (the `ncon` deepest, in that order, if there are more), then unused slots (dist INACTIVE)."""
    tops, valid, a, b, _ = _window(h, pos, mat, radius, half, subgrid)
    dist, cpos, n = jax.vmap(prism_contact, in_axes=(0, None, None, None, None))(tops, -h.size[3], a, b, radius)
    active = valid & (dist < 0.0)

    # keep the ncon deepest, in MuJoCo C's order (pad to at least ncon candidates)
    n_prism = dist.shape[0]
    if n_prism < ncon:
        pad = ncon - n_prism
        dist = jnp.concatenate([dist, jnp.full(pad, INACTIVE, dist.dtype)])
        cpos = jnp.concatenate([cpos, jnp.zeros((pad, 3), cpos.dtype)])
        n = jnp.concatenate([n, jnp.zeros((pad, 3), n.dtype)])
        active = jnp.concatenate([active, jnp.zeros(pad, bool)])
    _, sel = jax.lax.top_k(jnp.where(active, -dist, -jnp.inf), ncon)
    order = jnp.where(active[sel], sel, sel + dist.shape[0])
    sel = sel[jnp.argsort(order)]
    keep = active[sel]
    dist = jnp.where(keep, dist[sel], INACTIVE)
    cpos, n = cpos[sel], n[sel]
    wpos = cpos @ h.mat.T + h.pos
    wn = n @ h.mat.T
    wn = jnp.where(keep[:, None], wn, jnp.array([0.0, 0.0, 1.0]) @ h.mat.T)
    frame = jax.vmap(mjx_math.make_frame)(wn)
    return dist, wpos, frame


def _windows(h, pos, mat, radius, half, subgrid: Tuple[int, int]):
    """`_window` for P geoms, each with its own height field pose (`h.pos` (P, 3), `h.mat` (P, 3, 3))."""
    return jax.vmap(lambda hp, hm, *g: _window(h.replace(pos=hp, mat=hm), *g, subgrid))(
        h.pos, h.mat, pos, mat, radius, half)


def hfield_group(h, pos, mat, radius, half, subgrid: Tuple[int, int], ncon: int, candidates: int):
    """The same contacts for P geoms at once (pos (P, 3), mat (P, 3, 3), radius (P,), half (P,); `h.pos` (P, 3),
    `h.mat` (P, 3, 3): the height field geom of each pair), testing exactly only the `candidates` prisms of the
    whole group with the lowest `_bound` (the others: never in contact unless more than `candidates` prisms pass
    the bound, when the shallowest-bounded are dropped).

    Most geoms of a robot are in the air at any time: of the group's P x Q prisms (27 x ~90 for the train set)
    a few dozen can touch, so the exact test (`prism_contact`, thousands of flops) runs on those only. With no
    prism dropped the result equals `hfield_geom`'s for every pair: the same contacts in the same slots.

    Returns (dist (P ncon,), pos (P ncon, 3), frame (P ncon, 3, 3)), pair after pair, as MJX's collider table
    expects."""
    tops, valid, a, b, bound = _windows(h, pos, mat, radius, half, subgrid)
    num_pairs, q_per = valid.shape
    k = min(int(candidates), num_pairs * q_per)
    cand = (valid & (bound < BOUND_SLACK)).reshape(-1)
    _, idx = jax.lax.top_k(jnp.where(cand, -bound.reshape(-1), -jnp.inf), k)
    p, q = idx // q_per, idx % q_per
    dist, cpos, n = jax.vmap(prism_contact, in_axes=(0, None, 0, 0, 0))(
        tops.reshape(-1, 3, 3)[idx], -h.size[3], a[p], b[p], radius[p])
    active = cand[idx] & (dist < 0.0)

    # per pair: the ncon deepest (ties: MuJoCo C's order), placed in MuJoCo C's order in the pair's slots
    same = p[:, None] == p[None, :]
    deeper = (dist[None, :] < dist[:, None]) | ((dist[None, :] == dist[:, None]) & (q[None, :] < q[:, None]))
    keep = active & (jnp.sum(same & active[None, :] & deeper, axis=1) < ncon)
    slot = jnp.sum(same & keep[None, :] & (q[None, :] < q[:, None]), axis=1)
    row = jnp.where(keep, p * ncon + slot, num_pairs * ncon)         # out of range: dropped by the scatter

    hmat, hpos = h.mat[p], h.pos[p]
    wpos = jnp.einsum("kij,kj->ki", hmat, cpos) + hpos
    frame = jax.vmap(mjx_math.make_frame)(jnp.einsum("kij,kj->ki", hmat, n))
    up = jax.vmap(mjx_math.make_frame)(h.mat[:, :, 2])                # unused slots: the field's normal
    out_dist = jnp.full(num_pairs * ncon, INACTIVE, dist.dtype).at[row].set(dist, mode="drop")
    out_pos = jnp.repeat(h.pos, ncon, axis=0).at[row].set(wpos, mode="drop")
    out_frame = jnp.repeat(up, ncon, axis=0).at[row].set(frame, mode="drop")
    return out_dist, out_pos, out_frame


def candidate_counts(h, pos, mat, radius, half, subgrid: Tuple[int, int]):
    """How many prisms of each geom pass the bound (the prisms `hfield_group` tests exactly), (P,): to size
    `candidates` (experiments, tests)."""
    _, valid, _, _, bound = _windows(h, pos, mat, radius, half, subgrid)
    return jnp.sum(valid & (bound < BOUND_SLACK), axis=1)


# ---- installation into MJX's collision table -------------------------------------------------------------------
RULES = ("mujoco", "mjx")
DEFAULT_PER_GEOM = 32       # contacts per (height field, geom) pair under the "mujoco" rule (MuJoCo C: up to 50)
DEFAULT_CANDIDATES = 96     # prisms per group of pairs tested exactly (`hfield_group`); 0: every prism
_MJX = {GeomType.SPHERE: collision_convex.hfield_sphere, GeomType.CAPSULE: collision_convex.hfield_capsule}
_RULE = contextvars.ContextVar("mjx_morph_hfield_contacts", default=("mujoco", DEFAULT_PER_GEOM, DEFAULT_CANDIDATES))


def _half(kind: GeomType, size):
    return size[..., 1] if kind == GeomType.CAPSULE else jnp.zeros_like(size[..., 0])


@functools.lru_cache(maxsize=None)
def _collider(kind: GeomType, rule: str, per_geom: int, candidates: int):
    if rule == "mjx":
        return _MJX[kind]
    if candidates <= 0:
        @collision_convex.collider(ncon=per_geom)
        def hfield_mujoco(h, g, subgrid_size):
            return hfield_geom(h, g.pos, g.mat, g.size[0], _half(kind, g.size), subgrid_size, per_geom)

        return hfield_mujoco

    def hfield_mujoco_group(m, d, key, geom):     # MJX's `collider` wrapper, without its vmap over the pairs
        g1, g2 = geom.T
        h = mesh.hfield(m, key.data_ids[0]).replace(pos=d.geom_xpos[g1], mat=d.geom_xmat[g1])
        size = m.geom_size[g2]
        return hfield_group(h, d.geom_xpos[g2], d.geom_xmat[g2], size[:, 0], _half(kind, size), key.subgrid_size,
                            per_geom, candidates)

    hfield_mujoco_group.ncon = per_geom
    return hfield_mujoco_group


class _Installed:
    """The table's entry for (height field, `kind`): the collider of the innermost `rule` block being traced,
    with that rule's number of contacts per pair (`ncon`, read by MJX when it sizes the contact arrays in
    `make_data` and when it runs the collider: both must happen under the same rule)."""

    def __init__(self, kind: GeomType):
        self.kind = kind

    @property
    def ncon(self) -> int:
        return _collider(self.kind, *_RULE.get()).ncon

    def __call__(self, m, d, key, geom):
        fn = _collider(self.kind, *_RULE.get())
        dist, pos, frame = fn(m, d, key, geom)
        if fn in _MJX.values():
            return dist, pos, frame
        # geoms that can never be active (model.INERT_MARGIN): unused slots, never picked by a contact budget
        return never_active_last(m, geom, dist, fn.ncon), pos, frame


def install() -> None:
    """Put the height-field sphere and capsule colliders into MJX's collision table (idempotent; done at import of
    mjx_morph.sim)."""
    for kind in (GeomType.SPHERE, GeomType.CAPSULE):
        collision_driver._COLLISION_FUNC[(GeomType.HFIELD, kind)] = _Installed(kind)


def check_rule(rule: str, per_geom: int = DEFAULT_PER_GEOM, candidates: int = DEFAULT_CANDIDATES) -> str:
    if rule not in RULES:
        raise ValueError(f"hfield_contacts={rule!r}: expected one of {', '.join(RULES)}")
    if not 2 <= int(per_geom) <= 50:
        raise ValueError(f"hfield_contacts_per_geom={per_geom}: expected 2..50 (MuJoCo C's cap is 50)")
    if int(candidates) < 0:
        raise ValueError(f"hfield_candidates={candidates}: expected 0 (test every prism) or a positive number of "
                         "prisms per group of pairs")
    return rule


@contextlib.contextmanager
def rule(name: str, per_geom: int = DEFAULT_PER_GEOM, candidates: int = DEFAULT_CANDIDATES) -> Iterator[None]:
    """Trace MJX (make_data and the steps) inside this block with height-field contacts of rule `name`:
    "mujoco" (MuJoCo C's, at most `per_geom` per geom; with `candidates` > 0 only that many prisms per group of
    pairs, those of lowest bound, are tested exactly: `hfield_group`) or "mjx" (MJX 3.17's own, 4 per geom)."""
    token = _RULE.set((check_rule(name, per_geom, candidates), int(per_geom), int(candidates)))
    try:
        yield
    finally:
        _RULE.reset(token)
