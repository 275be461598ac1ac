"""The self-collision pair cut: which slot pairs of a robot set can ever touch.

MJX's candidate contact pairs are static: with self-collision on, every pair of bodies of the shared tree that is
not parent-child becomes a pair, and each pair allocates contact constraint rows in every env, whether or not its
geoms can ever meet. Most cannot: a joint only turns through its range, so the geoms of two limbs on opposite sides
of the torso stay far apart in every pose. This module finds, for each robot alone, the pairs of its geoms (torso
sphere and limb capsules, bodies not parent-child) that can come within `margin` of each other for some joint
angles in the joint ranges widened by `slack` on each side (the joint limits are soft and can be exceeded a little),
and maps them onto the slots of the shared tree: a slot pair is kept when some robot that uses both slots can make
its two geoms touch. `padding.py` excludes every other slot pair (`<contact><exclude>`), the same list for every
robot of the set, so the static MJX structure stays shared.

Indices: a robot's *nodes* are 0 = torso and 1 + i = limb i (body id - 1 in the robot's own compiled model, and the
policy's token order); a node pair is (a, b) with a < b. Slot pairs are (s, t) with s < t.

The decision for one geom pair. With
    f(q) = (distance between the two geom segments) - (sum of the two radii)
(a sphere is a segment of length zero), f(q) <= margin is "can touch". f depends only on the angles of the *moving
joints*: the hinges of the bodies on the paths from the lowest common ancestor body (LCA) of the two bodies down to
each of them; the LCA's own hinges, the free joint and every other hinge move both geoms rigidly together, or not
at all. Over the box of the moving joints' ranges widened by `slack`:
1. random poses (many with several joints at a limit: some pairs touch only there), then projected gradient descent
   of f from the best of them; a pose with f <= margin proves that the pair touches;
2. otherwise a branch-and-bound: a box is dropped when a lower bound of f over it is above the margin, the pair
   touches as soon as f <= margin at a box centre, other boxes are split in two along the joint that loosens the
   bound most. The boxes of all the robot's pairs are evaluated together, one level at a time, with a vectorised
   forward kinematics (`forward_kinematics`, MuJoCo's recursion). A pair whose search exceeds its box budget is
   kept (counted as unresolved): the cut never drops a pair that it has not proved apart.

Why the bounds are conservative. The lower bound of f over a box (centre c, half-widths h) is the larger of two
bounds, each valid for every pose q of the box:
(1) Chord bound. Turning hinge j by an angle d moves a point at distance rho from its axis by the chord
    2 rho sin(|d| / 2). Moving both geoms by one rigid motion leaves their distance unchanged, so turning j changes
    the distance by at most the chord times min(rho_a, rho_b), the largest distances of the two geoms from the axis
    (turning a one way about the axis is, relative to a, turning b the other way). Over the box, rho is at most its
    value at c plus the chords of the joints between that axis and the geom (the only joints that move the geom
    relative to the axis), and at most a pose-independent bound (`chain_reach`: the triangle inequality along the
    rigid chain of joint anchors). Changing the angles one at a time from c to q gives
    f(q) >= f(c) - sum_j 2 sin(h_j / 2) min(R_aj, R_bj) with R those bounds on rho.
(2) Separating-plane bound. With n the unit vector between the closest points at c, the distance between the
    segments is at least min over a's ends e of n.e - max over b's ends of n.e in every pose (n.x is linear, so its
    extremes on a segment are at the ends; at c the bound equals the distance). Each n.e(q) is a smooth function of
    the angles that move e, and Taylor's theorem with the Lagrange remainder bounds it by
    n.e(c) +- (sum_j |g_j| h_j + 1/2 sum_jk h_j h_k M_jk), where g_j = n.(axis_j x (e - anchor_j)) at c and
    M_jk, a bound of |d^2 e / dq_j dq_k|, is the bound R of (1) on e's distance from the deeper of the two axes.
Bound (1) is the better one for large boxes, (2) for small ones (it does not count motion along the plane).

The result for a robot is cached per geometry (a hash of its `Kinematics`: variants that change dynamics only share
it) and per margin, slack and budget, so building several envs of one set in a process computes it once; it is also
kept on disk (`pair_cache_dir`: ~/.cache/mjx_morph/pairs, or $MJX_MORPH_PAIR_CACHE), so other processes read it
instead of searching again; a set of many new geometries is searched in several processes (`robots_pairs`).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
import warnings
from functools import lru_cache, partial
from pathlib import Path
from typing import NamedTuple, Sequence

import mujoco
import numpy as np

from ..unimal.mjcf import compile_model
from ..unimal.morphology import Morphology
from .processes import process_map, processes_for
from .supertree import SharedTree

MARGIN = 0.01          # m: a pair is kept when its geoms can come this close
SLACK = 0.1            # rad: joint ranges widened by this on each side
BOX_BUDGET = 5_000     # boxes per geom pair before the search gives up and keeps the pair
RANDOM_SAMPLES = 128   # random poses per pair tried before the search (finds most touching pairs at once)
DESCENT_STARTS = 8     # ... the best of them then descend along the gradient of the distance
DESCENT_STEPS = 40
CHUNK = 32_768        # boxes evaluated at once (bounds the memory of one evaluation)


# ---- the robot's kinematics ---------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Kinematics:
    """A robot's kinematic tree read from its own compiled MuJoCo model, in the torso's frame.

    Node n is body n + 1 of the compiled model (0 = torso); hinge joint k is joint k + 1 (joint 0 is the free joint).
    parent[n]          parent node (-1 for the torso).
    body_pos, body_rot position (n, 3) and rotation (n, 3, 3) of a node's frame in its parent's frame at zero angles.
    joint_node[k]      node of hinge k; joints of one node are applied in joint order.
    joint_pos, joint_axis  anchor and unit axis of hinge k in its node's frame (mm.jnt_pos, mm.jnt_axis).
    joint_lo, joint_hi range of hinge k (rad).
    seg[n]             the two ends (2, 3) of node n's geom segment in its node's frame (equal for a sphere).
    radius[n]          the geom's radius.
    """
    parent: np.ndarray
    body_pos: np.ndarray
    body_rot: np.ndarray
    joint_node: np.ndarray
    joint_pos: np.ndarray
    joint_axis: np.ndarray
    joint_lo: np.ndarray
    joint_hi: np.ndarray
    seg: np.ndarray
    radius: np.ndarray

    @property
    def num_nodes(self) -> int:
        return len(self.parent)

    @property
    def num_joints(self) -> int:
        return len(self.joint_node)

    def joints_of(self, node: int) -> list[int]:
        return [k for k in range(self.num_joints) if self.joint_node[k] == node]

    def path_up(self, node: int, stop: int) -> list[int]:
        """Nodes from `node` up to, not including, its ancestor `stop`, top-down."""
        out = []
        while node != stop:
            out.append(node)
            node = int(self.parent[node])
        return out[::-1]

    def ancestors(self, node: int) -> list[int]:
        """`node` and its ancestors up to the torso, bottom-up."""
        out = [node]
        while self.parent[out[-1]] >= 0:
            out.append(int(self.parent[out[-1]]))
        return out


def kinematics(mm: mujoco.MjModel) -> Kinematics:
    """The `Kinematics` of a robot's own compiled model (one free joint on body 1, hinges below, one sphere or
    capsule geom per body)."""
    nb = mm.nbody - 1
    if mm.jnt_type[0] != mujoco.mjtJoint.mjJNT_FREE or mm.jnt_bodyid[0] != 1:
        raise ValueError("kinematics: expected a free joint on body 1")
    if np.any(mm.jnt_type[1:] != mujoco.mjtJoint.mjJNT_HINGE):
        raise ValueError("kinematics: expected hinge joints below the free joint")
    body_rot = np.zeros((nb, 3, 3))
    for n in range(nb):
        mujoco.mju_quat2Mat(body_rot[n].reshape(-1), mm.body_quat[n + 1])
    seg = np.zeros((nb, 2, 3))
    radius = np.zeros(nb)
    for n in range(nb):
        if mm.body_geomnum[n + 1] != 1:
            raise ValueError(f"kinematics: body {n + 1} has {mm.body_geomnum[n + 1]} geoms, expected 1")
        g = mm.body_geomadr[n + 1]
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, mm.geom_quat[g])
        half = 0.0
        if mm.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE:
            half = mm.geom_size[g, 1]
        elif mm.geom_type[g] != mujoco.mjtGeom.mjGEOM_SPHERE:
            raise ValueError(f"kinematics: geom {g} is neither a sphere nor a capsule")
        d = rot.reshape(3, 3)[:, 2] * half
        seg[n] = [mm.geom_pos[g] - d, mm.geom_pos[g] + d]
        radius[n] = mm.geom_size[g, 0]
    hinge = np.arange(1, mm.njnt)
    return Kinematics(
        parent=np.asarray(mm.body_parentid[1:], int) - 1,
        body_pos=np.array(mm.body_pos[1:], float), body_rot=body_rot,
        joint_node=np.asarray(mm.jnt_bodyid[hinge], int) - 1,
        joint_pos=np.array(mm.jnt_pos[hinge], float), joint_axis=np.array(mm.jnt_axis[hinge], float),
        joint_lo=np.array(mm.jnt_range[hinge, 0], float), joint_hi=np.array(mm.jnt_range[hinge, 1], float),
        seg=seg, radius=radius)


def _times(r: np.ndarray, m: np.ndarray) -> np.ndarray:
    """r @ m for a batch of matrices r (N, 3, 3) and one matrix (3, 3) or vector (3,) m (one BLAS product)."""
    n = len(r)
    return (r.reshape(3 * n, 3) @ m).reshape((n, 3, 3) if m.ndim == 2 else (n, 3))


def _skew(v: np.ndarray) -> np.ndarray:
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


class Poses(NamedTuple):
    """A batch of N poses of a robot, in the torso's frame (torso at the origin, unrotated)."""
    rot: np.ndarray      # (N, nodes, 3, 3) node frames
    pos: np.ndarray      # (N, nodes, 3)
    anchor: np.ndarray   # (N, joints, 3) hinge anchors (points of the hinge axes)
    axis: np.ndarray     # (N, joints, 3) unit hinge axes


def forward_kinematics(kin: Kinematics, q: np.ndarray) -> Poses:
    """The poses for a batch of hinge angles `q` (N, num_joints). The recursion of MuJoCo's `mj_kinematics`: a
    node's frame is its parent's frame times its body offset; each of its hinges then turns it about the hinge's
    anchor, in joint order (a turn by angle t about the unit axis u is I + sin t [u] + (1 - cos t) [u]^2,
    Rodrigues' formula, with [u] the cross-product matrix)."""
    n = len(q)
    rot = np.empty((n, kin.num_nodes, 3, 3))
    pos = np.empty((n, kin.num_nodes, 3))
    anchor = np.empty((n, kin.num_joints, 3))
    axis = np.empty((n, kin.num_joints, 3))
    sin, one_minus_cos = np.sin(q), 1.0 - np.cos(q)
    for b in range(kin.num_nodes):
        p = kin.parent[b]
        if p < 0:   # the torso: its free joint places it; here at the origin, unrotated
            r, x = np.broadcast_to(np.eye(3), (n, 3, 3)).copy(), np.zeros((n, 3))
        else:
            r = _times(rot[:, p], kin.body_rot[b])
            x = pos[:, p] + _times(rot[:, p], kin.body_pos[b])
        for k in kin.joints_of(b):
            anchor[:, k] = x + _times(r, kin.joint_pos[k])
            axis[:, k] = _times(r, kin.joint_axis[k])
            u = _skew(kin.joint_axis[k])
            r = r + sin[:, k, None, None] * _times(r, u) + one_minus_cos[:, k, None, None] * _times(r, u @ u)
            x = anchor[:, k] - _times(r, kin.joint_pos[k])
        rot[:, b], pos[:, b] = r, x
    return Poses(rot, pos, anchor, axis)


def segments(kin: Kinematics, poses: Poses) -> np.ndarray:
    """The geom segments (N, nodes, 2, 3) of a batch of poses."""
    return poses.pos[:, :, None, :] + np.einsum("nbij,bkj->nbki", poses.rot, kin.seg)


# ---- segment distance ---------------------------------------------------------------------------------------------
def closest_points(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distance between the segments [p0, p1] and [q0, q1] (arrays (..., 3); a segment may have length zero) and
    the parameters s, t of a closest pair of points p0 + s (p1 - p0), q0 + t (q1 - q0).

    |p0 + s u - q0 - t v|^2 is a convex quadratic over the square s, t in [0, 1]: its minimum is at the interior
    stationary point when that lies in the square, else on one of the four edges, where fixing one parameter leaves
    a 1-D convex quadratic minimised by clamping its stationary point. The distance is the smallest of these five
    candidates (the interior one clamped into the square, so every candidate is a pair of points of the segments)."""
    u, v, w = p1 - p0, q1 - q0, p0 - q0
    a = np.einsum("...i,...i", u, u)
    b = np.einsum("...i,...i", u, v)
    e = np.einsum("...i,...i", v, v)
    c = np.einsum("...i,...i", u, w)
    f = np.einsum("...i,...i", v, w)
    tiny = 1e-300
    det = a * e - b * b
    ok = det > 1e-12 * np.maximum(a * e, tiny)
    det = np.where(ok, det, 1.0)
    s_in = np.where(ok, np.clip((b * f - c * e) / det, 0.0, 1.0), 0.0)
    t_in = np.where(ok, np.clip((a * f - b * c) / det, 0.0, 1.0), 0.0)

    def best_t(s):      # closest t on [q0, q1] to the point p0 + s u
        return np.where(e > tiny, np.clip((f + s * b) / np.maximum(e, tiny), 0.0, 1.0), 0.0)

    def best_s(t):      # closest s on [p0, p1] to the point q0 + t v
        return np.where(a > tiny, np.clip((t * b - c) / np.maximum(a, tiny), 0.0, 1.0), 0.0)

    zero, one = np.zeros_like(a), np.ones_like(a)
    dist = s_out = t_out = None
    for s, t in [(s_in, t_in), (zero, best_t(zero)), (one, best_t(one)), (best_s(zero), zero), (best_s(one), one)]:
        d = np.linalg.norm(w + s[..., None] * u - t[..., None] * v, axis=-1)
        if dist is None:
            dist, s_out, t_out = d, s, t
        else:
            better = d < dist
            dist, s_out, t_out = np.where(better, d, dist), np.where(better, s, s_out), np.where(better, t, t_out)
    return dist, s_out, t_out


def segment_distance(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """Distance between the segments [p0, p1] and [q0, q1] (see `closest_points`)."""
    return closest_points(p0, p1, q0, q1)[0]


# ---- one robot ----------------------------------------------------------------------------------------------------
def candidate_node_pairs(kin: Kinematics) -> list[tuple[int, int]]:
    """Node pairs (a, b), a < b, that are not parent-child: the pairs MJX checks with self-collision on."""
    return [(a, b) for a in range(kin.num_nodes) for b in range(a + 1, kin.num_nodes)
            if kin.parent[b] != a and kin.parent[a] != b]


def _lca(kin: Kinematics, a: int, b: int) -> int:
    up = set(kin.ancestors(a))
    return next(n for n in kin.ancestors(b) if n in up)


def moving_joints(kin: Kinematics, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
    """Masks (num_joints,) of the hinges on the path from the lowest common ancestor of nodes a and b down to a
    (first mask) and down to b (second), the LCA's own hinges excluded: the only joints that move the two geoms
    relative to each other. Along one path, a joint's index grows with depth (MuJoCo numbers joints depth-first)."""
    lca = _lca(kin, a, b)
    out = []
    for end in (a, b):
        path = set(kin.path_up(end, lca))
        out.append(np.array([int(n) in path for n in kin.joint_node]))
    return out[0], out[1]


def chain_reach(kin: Kinematics, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
    """Bounds (num_joints,) valid in every pose on the distance from each moving joint's anchor to any point of
    node a's geom segment (first array) and of node b's (second); inf for the other joints.

    The chain from a's geom up to the lowest common ancestor and down to b's geom passes through the anchors of the
    moving joints; two consecutive points of it are fixed in one rigid frame (two anchors of one node, a node's last
    anchor and its child's first anchor, the two top anchors in the ancestor's frame, a geom's end and the nearest
    anchor), so their distance is a constant, and the triangle inequality bounds the distance between any two
    points of the chain by the sum of the constants in between. A node without hinges counts its origin as its
    anchor."""
    lca = _lca(kin, a, b)

    def points(node):   # the node's anchors in its final frame, in joint order, and their joint ids
        js = kin.joints_of(node)
        return ([kin.joint_pos[k] for k in js] or [np.zeros(3)]), (js or [None])

    def entry(node):    # the node's first anchor in its parent's final frame
        return kin.body_pos[node] + kin.body_rot[node] @ points(node)[0][0]

    def down(end):      # the path to `end`, its anchors top-down as (joint, distance to the previous anchor), and
                        # `end`'s last anchor in its own frame
        path = kin.path_up(end, lca)
        out = []
        for i, n in enumerate(path):
            pts, js = points(n)
            for k, (pt, j) in enumerate(zip(pts, js)):
                if k:
                    link = np.linalg.norm(pt - pts[k - 1])
                elif i:
                    link = np.linalg.norm(entry(n) - points(path[i - 1])[0][-1])
                else:
                    link = 0.0      # the top anchor: linked to the other side below
                out.append((j, float(link)))
        last = points(end)[0][-1] if path else None
        return path, out, last

    path_a, chain_a, last_a = down(a)
    path_b, chain_b, last_b = down(b)
    seg_len = lambda node, pt: float(np.max(np.linalg.norm(kin.seg[node] - pt, axis=1)))
    # the link between the two top anchors (or a top anchor and the ancestor's own geom)
    if path_a and path_b:
        top = float(np.linalg.norm(entry(path_a[0]) - entry(path_b[0])))
    elif path_a:
        top = seg_len(lca, entry(path_a[0]))
    else:
        top = seg_len(lca, entry(path_b[0]))
    # the chain as (joint or None, distance bound to the previous point), from a's geom to b's geom
    items = [(None, 0.0)]
    for i, (j, _) in enumerate(chain_a[::-1]):            # up from a's geom
        items.append((j, seg_len(a, last_a) if i == 0 else chain_a[::-1][i - 1][1]))
    for i, (j, link) in enumerate(chain_b):               # down to b's geom
        items.append((j, top if i == 0 else link))
    items.append((None, seg_len(b, last_b) if path_b else top))
    cum = np.cumsum([d for _, d in items])
    to_a = np.full(kin.num_joints, np.inf)
    to_b = np.full(kin.num_joints, np.inf)
    for i, (j, _) in enumerate(items):
        if j is not None:
            to_a[j] = cum[i] - cum[0]
            to_b[j] = cum[-1] - cum[i]
    return to_a, to_b


@dataclasses.dataclass(frozen=True)
class RobotPairs:
    """The outcome for one robot: node pairs that can touch (kept), and how the search went."""
    candidates: tuple[tuple[int, int], ...]   # node pairs that are not parent-child
    touching: frozenset                       # node pairs shown to come within the margin
    unresolved: frozenset                     # node pairs kept because the box budget ran out
    boxes: int                                # poses evaluated (random samples and box centres)

    @property
    def kept(self) -> frozenset:
        return self.touching | self.unresolved


def robot_pairs(m: Morphology, margin: float = MARGIN, slack: float = SLACK, budget: int = BOX_BUDGET,
                seed: int = 0) -> RobotPairs:
    """The node pairs of robot `m` whose geoms can come within `margin` for joint angles in the ranges widened by
    `slack` (cached per geometry and settings)."""
    return robots_pairs([m], margin, slack, budget, seed, processes=1)[0]


def robots_pairs(robots: Sequence[Morphology], margin: float = MARGIN, slack: float = SLACK,
                 budget: int = BOX_BUDGET, seed: int = 0, processes: int | None = None) -> list[RobotPairs]:
    """`robot_pairs` of each robot. The outcome depends on the robot's `Kinematics` alone, so it is cached per
    geometry (`geometry_digest`): robots that differ only in dynamics (density, gear, armature, damping: two thirds
    of the 2400 variants) share their base robot's search. The searches left run in `processes` processes (default
    `processes.processes_for`): the 900 distinct geometries of the variants take minutes on one core."""
    keys = [(geometry_digest(m), float(margin), float(slack), int(budget), int(seed)) for m in robots]
    disk = pair_cache_dir()
    todo = {}
    for key, m in zip(keys, robots):
        if key in _FOUND:
            continue
        kept = None if disk is None else _read_cached(disk, key)
        if kept is not None:
            _FOUND[key] = kept
        else:
            todo.setdefault(key, _kinematics(m))
    if todo:
        n = processes_for(len(todo)) if processes is None else max(1, min(int(processes), len(todo)))
        for key, found in zip(todo, _search_all(list(todo.values()), n, margin, slack, budget, seed)):
            _FOUND[key] = found
            if disk is not None:
                _write_cached(disk, key, found)
    return [_FOUND[key] for key in keys]


_FOUND: dict[tuple, RobotPairs] = {}     # (geometry digest, margin, slack, budget, seed) -> the search's outcome

#: where searches are kept between processes: $MJX_MORPH_PAIR_CACHE ("" for none), else ~/.cache/mjx_morph/pairs
PAIR_CACHE_ENV = "MJX_MORPH_PAIR_CACHE"


def pair_cache_dir() -> Path | None:
    """The folder of the searches kept on disk (one JSON file per geometry and settings, valid for this version of
    this module alone), or None when `$MJX_MORPH_PAIR_CACHE` is set empty."""
    path = os.environ.get(PAIR_CACHE_ENV, str(Path("~/.cache/mjx_morph/pairs")))
    return Path(path).expanduser() if path else None


@lru_cache(maxsize=1)
def _code_digest() -> str:
    """A hash of this module's source: a search kept by other code is not read."""
    return hashlib.sha256(Path(__file__).read_bytes()).hexdigest()[:16]


def _cache_file(disk: Path, key: tuple) -> Path:
    return disk / (hashlib.sha256(repr((key, _code_digest())).encode()).hexdigest() + ".json")


def _read_cached(disk: Path, key: tuple) -> RobotPairs | None:
    """The search kept on disk for `key`; None when there is none (or it cannot be read: it is searched again and
    rewritten, with a warning)."""
    f = _cache_file(disk, key)
    if not f.exists():
        return None
    try:
        d = json.loads(f.read_text())
        pairs = lambda name: frozenset((int(a), int(b)) for a, b in d[name])
        return RobotPairs(candidates=tuple((int(a), int(b)) for a, b in d["candidates"]),
                          touching=pairs("touching"), unresolved=pairs("unresolved"), boxes=int(d["boxes"]))
    except (OSError, ValueError, KeyError, TypeError) as e:
        warnings.warn(f"{f}: unreadable kept self-collision pair search ({type(e).__name__}: {e}); searching again",
                      RuntimeWarning, stacklevel=3)
        return None


def _write_cached(disk: Path, key: tuple, found: RobotPairs) -> None:
    """Keep `found` on disk (written whole or not at all; a folder that cannot be written only warns)."""
    f = _cache_file(disk, key)
    try:
        disk.mkdir(parents=True, exist_ok=True)
        tmp = f.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(json.dumps({"candidates": [list(p) for p in found.candidates],
                                   "touching": sorted(list(p) for p in found.touching),
                                   "unresolved": sorted(list(p) for p in found.unresolved), "boxes": found.boxes}))
        os.replace(tmp, f)
    except OSError as e:
        warnings.warn(f"{disk}: cannot keep the self-collision pair search there ({e}); set ${PAIR_CACHE_ENV} to "
                      f"another folder, or empty for none", RuntimeWarning, stacklevel=3)


@lru_cache(maxsize=None)
def _kinematics(m: Morphology) -> Kinematics:
    return kinematics(compile_model(m))


@lru_cache(maxsize=None)
def geometry_digest(m: Morphology) -> str:
    """A hash of everything the search reads of robot `m` (its `Kinematics`: tree, frames, hinge anchors, axes and
    ranges, geom segments and radii)."""
    kin = _kinematics(m)
    h = hashlib.sha256()
    for f in dataclasses.fields(kin):
        a = np.ascontiguousarray(getattr(kin, f.name))
        h.update(f"{f.name}{a.dtype}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _search_all(kins: list[Kinematics], processes: int, margin: float, slack: float, budget: int,
                seed: int) -> list[RobotPairs]:
    """`search_pairs` of each robot, in `processes` processes (`processes.process_map`)."""
    search = partial(search_pairs, margin=margin, slack=slack, budget=budget, seed=seed)
    return process_map(search, kins, processes, "the self-collision pair search")


def pair_gap(kin: Kinematics, q: np.ndarray, pa: np.ndarray, pb: np.ndarray) -> np.ndarray:
    """f (segment distance minus radii) for rows of hinge angles `q` (N, num_joints) and node pairs (pa, pb) (N,)."""
    seg = segments(kin, forward_kinematics(kin, q))
    rows = np.arange(len(q))
    sa, sb = seg[rows, pa], seg[rows, pb]
    return segment_distance(sa[:, 0], sa[:, 1], sb[:, 0], sb[:, 1]) - kin.radius[pa] - kin.radius[pb]


def box_bound(kin: Kinematics, centre: np.ndarray, half: np.ndarray, pa: np.ndarray, pb: np.ndarray,
              on_a: np.ndarray, on_b: np.ndarray, cap_a: np.ndarray, cap_b: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For boxes of hinge angles (centres and half-widths (N, num_joints), `half` 0 for the joints that do not
    move the pair), and their node pairs (pa, pb) (N,): f at the centres (N,), a lower bound of f over each box
    (N,), and a score per joint (N, num_joints) of how much its half-width loosens the bound (the search splits
    the joint with the largest). `on_a`, `on_b` are the rows' `moving_joints` masks, `cap_a`, `cap_b` their
    `chain_reach` bounds. The two bounds (the larger is returned) are explained in the module docstring."""
    poses = forward_kinematics(kin, centre)
    seg = segments(kin, poses)
    rows = np.arange(len(centre))
    sa, sb = seg[rows, pa], seg[rows, pb]                                          # (N, 2, 3)
    dist, s, t = closest_points(sa[:, 0], sa[:, 1], sb[:, 0], sb[:, 1])
    radii = kin.radius[pa] + kin.radius[pb]
    gap = dist - radii
    turn = 2.0 * np.sin(np.minimum(half, np.pi) / 2.0)     # chord of the largest turn, per unit of radius

    def off_axis(ends):   # (N, J) largest distance of the segment `ends` (N, 2, 3) from each hinge axis
        rel = ends[:, None, :, :] - poses.anchor[:, :, None, :]                      # (N, J, 2, 3)
        along = np.einsum("njei,nji->nje", rel, poses.axis)
        return np.linalg.norm(rel - along[..., None] * poses.axis[:, :, None, :], axis=-1).max(axis=-1)

    def reach(ends, near, far, cap):
        """(N, J) bound over the box on the distance of a geom segment from each axis of the chain: the distance
        at the centre plus the chords of the joints between that axis and the geom, or the pose-independent `cap`
        when smaller. `near`: the joints of the path down to the geom (deepest is nearest), `far`: those of the
        other path (shallowest is nearest)."""
        off = off_axis(ends)
        out = np.zeros_like(off)
        acc = np.zeros(len(centre))
        for j in range(kin.num_joints - 1, -1, -1):     # own path, from the geom up
            out[:, j] = np.where(near[:, j], np.minimum(off[:, j] + acc, cap[:, j]), out[:, j])
            acc += np.where(near[:, j], turn[:, j] * out[:, j], 0.0)
        for j in range(kin.num_joints):                 # through the common ancestor, down the other path
            out[:, j] = np.where(far[:, j], np.minimum(off[:, j] + acc, cap[:, j]), out[:, j])
            acc += np.where(far[:, j], turn[:, j] * out[:, j], 0.0)
        return out

    reach_a, reach_b = reach(sa, on_a, on_b, cap_a), reach(sb, on_b, on_a, cap_b)
    # bound 1: each joint's turn changes the distance by at most its chord times the nearer geom's axis distance
    share = np.where(on_a | on_b, turn * np.minimum(reach_a, reach_b), 0.0)
    lower1 = gap - share.sum(axis=1)
    # bound 2: the plane between the closest points at the centre separates the two geoms by at least
    # min over a's ends of n.e - max over b's ends of n.e; each n.e is bounded by a second-order Taylor expansion
    ca = sa[:, 0] + s[:, None] * (sa[:, 1] - sa[:, 0])
    cb = sb[:, 0] + t[:, None] * (sb[:, 1] - sb[:, 0])
    n = (ca - cb) / np.maximum(dist, 1e-12)[:, None]
    n_x_axis = np.cross(n[:, None, :], poses.axis)                                   # (N, J, 3)

    def spread(ends, on, rch):
        """(N, 2) bound on how much n.e can move inside the box for the two ends, and the per-joint score."""
        h = np.where(on, half, 0.0)
        grad = np.einsum("neji,nji->nej", ends[:, :, None, :] - poses.anchor[:, None, :, :], n_x_axis)   # (N, 2, J)
        lin = np.abs(grad) @ h[:, :, None]                                             # (N, 2, 1)
        above = np.cumsum(h, axis=1) - h                                               # sum of h over shallower joints
        curv = 0.5 * np.sum(np.where(on, rch, 0.0) * h * (h + 2.0 * above), axis=1)  # (N,)
        score = h * (np.abs(grad).max(axis=1) + np.where(on, rch, 0.0) * h.sum(axis=1, keepdims=True))
        return lin[:, :, 0] + curv[:, None], score

    da, score_a = spread(sa, on_a, reach_a)
    db, score_b = spread(sb, on_b, reach_b)
    na = np.einsum("nei,ni->ne", sa, n)
    nb = np.einsum("nei,ni->ne", sb, n)
    lower2 = np.min(na - da, axis=1) - np.max(nb + db, axis=1) - radii
    lower2 = np.where(dist > 1e-9, lower2, -np.inf)
    use2 = lower2 > lower1
    return gap, np.maximum(lower1, lower2), np.where(use2[:, None], score_a + score_b, share)


def descend(kin: Kinematics, q: np.ndarray, lo: np.ndarray, hi: np.ndarray, pa: np.ndarray, pb: np.ndarray,
            on_a: np.ndarray, on_b: np.ndarray, steps: int = DESCENT_STEPS) -> np.ndarray:
    """The smallest f found by projected gradient descent in the boxes [lo, hi] (N, num_joints) from the poses `q`
    (N, num_joints), for node pairs (pa, pb): finds touching poses that random samples miss. The gradient of the
    distance is n . (axis_j x (closest point - anchor_j)) for the joints moving a (minus that at b's closest point
    for those moving b), with n the unit vector between the closest points; the step length adapts per row."""
    rows = np.arange(len(q))
    step = np.full(len(q), 0.3)
    best = np.full(len(q), np.inf)
    for _ in range(steps):
        poses = forward_kinematics(kin, q)
        seg = segments(kin, poses)
        sa, sb = seg[rows, pa], seg[rows, pb]
        dist, s, t = closest_points(sa[:, 0], sa[:, 1], sb[:, 0], sb[:, 1])
        gap = dist - kin.radius[pa] - kin.radius[pb]
        improved = gap < best
        step = np.where(improved, step * 1.5, step * 0.5)
        best = np.minimum(best, gap)
        ca = sa[:, 0] + s[:, None] * (sa[:, 1] - sa[:, 0])
        cb = sb[:, 0] + t[:, None] * (sb[:, 1] - sb[:, 0])
        n = (ca - cb) / np.maximum(dist, 1e-12)[:, None]
        n_x_axis = np.cross(n[:, None, :], poses.axis)
        grad = (np.where(on_a, np.einsum("nji,nji->nj", ca[:, None, :] - poses.anchor, n_x_axis), 0.0)
                - np.where(on_b, np.einsum("nji,nji->nj", cb[:, None, :] - poses.anchor, n_x_axis), 0.0))
        size = np.linalg.norm(grad, axis=1, keepdims=True)
        q_next = np.clip(q - step[:, None] * grad / np.maximum(size, 1e-12), lo, hi)
        # a rejected step goes back to the best pose so far: keep the pose only where it improved
        q = np.where(improved[:, None], q_next, q)
        if not np.any(step > 1e-4):
            break
    return best


def _in_chunks(kin, centre, half, pid, pa, pb, on_a, on_b, cap_a, cap_b):
    """`box_bound` of boxes of the pairs `pid` (the other arrays are per pair), CHUNK boxes at a time."""
    out = []
    for i in range(0, len(pid), CHUNK):
        p = pid[i:i + CHUNK]
        out.append(box_bound(kin, centre[i:i + CHUNK], half[i:i + CHUNK], pa[p], pb[p], on_a[p], on_b[p], cap_a[p],
                             cap_b[p]))
    return tuple(np.concatenate(x) for x in zip(*out))


def search_pairs(kin: Kinematics, margin: float = MARGIN, slack: float = SLACK, budget: int = BOX_BUDGET,
                 seed: int = 0) -> RobotPairs:
    """Samples, descent and branch-and-bound (module docstring) for all candidate pairs of one robot at once."""
    pairs = candidate_node_pairs(kin)
    if not pairs:
        return RobotPairs((), frozenset(), frozenset(), 0)
    P, J = len(pairs), kin.num_joints
    pa = np.array([p[0] for p in pairs])
    pb = np.array([p[1] for p in pairs])
    masks = [moving_joints(kin, a, b) for a, b in pairs]
    on_a = np.stack([m[0] for m in masks])
    on_b = np.stack([m[1] for m in masks])
    moves = on_a | on_b
    caps = [chain_reach(kin, a, b) for a, b in pairs]
    cap_a = np.stack([c[0] for c in caps])
    cap_b = np.stack([c[1] for c in caps])
    lo = np.where(moves, kin.joint_lo - slack, 0.0)
    hi = np.where(moves, kin.joint_hi + slack, 0.0)
    touching = np.zeros(P, bool)
    # random poses first, most of them with many joints at a limit: most pairs that touch do so in a large part
    # of the box, many of the others only with some joints at their limits
    rng = np.random.default_rng(seed)
    pid = np.repeat(np.arange(P), RANDOM_SAMPLES)
    u = rng.random((len(pid), J))
    at_limit = rng.random((len(pid), J)) < np.tile(np.linspace(0.0, 0.9, RANDOM_SAMPLES), P)[:, None]
    u = np.where(at_limit, np.round(u), u)
    q = lo[pid] + u * (hi[pid] - lo[pid])
    gap = pair_gap(kin, q, pa[pid], pb[pid])
    np.logical_or.at(touching, pid, gap <= margin)
    boxes = len(pid)
    # gradient descent from the best samples of the pairs still undecided
    order = np.lexsort((gap, pid))                      # by pair, then by gap
    rank = np.arange(len(pid)) - np.searchsorted(pid[order], pid[order])
    start = order[(rank < DESCENT_STARTS) & ~touching[pid[order]]]
    if len(start):
        p_ = pid[start]
        best = descend(kin, q[start], lo[p_], hi[p_], pa[p_], pb[p_], on_a[p_], on_b[p_])
        np.logical_or.at(touching, p_, best <= margin)
        boxes += len(start) * DESCENT_STEPS
    # breadth-first branch-and-bound over the undecided pairs
    pid = np.nonzero(~touching)[0]
    centre, half = (lo[pid] + hi[pid]) / 2, (hi[pid] - lo[pid]) / 2
    spent = np.zeros(P, int)
    unresolved = np.zeros(P, bool)
    while len(pid):
        # a pair whose next level would take it over the budget is given up, and kept
        count = np.bincount(pid, minlength=P)
        over = spent + count > budget
        unresolved |= over
        live = ~over[pid]
        pid, centre, half = pid[live], centre[live], half[live]
        spent += np.bincount(pid, minlength=P)
        boxes += len(pid)
        if not len(pid):
            break
        gap, lower, score = _in_chunks(kin, centre, half, pid, pa, pb, on_a, on_b, cap_a, cap_b)
        np.logical_or.at(touching, pid, gap <= margin)
        alive = (lower <= margin) & ~touching[pid]
        pid, centre, half, score = pid[alive], centre[alive], half[alive], score[alive]
        rows = np.arange(len(pid))
        dim = np.argmax(score, axis=1)
        half = half.copy()
        half[rows, dim] /= 2
        step = np.zeros_like(half)
        step[rows, dim] = half[rows, dim]
        pid = np.concatenate([pid, pid])
        centre = np.concatenate([centre - step, centre + step])
        half = np.concatenate([half, half])
    as_set = lambda mask: frozenset(p for p, k in zip(pairs, mask) if k)
    return RobotPairs(tuple(pairs), as_set(touching), as_set(unresolved), int(boxes))


def sampled_touching_pairs(m: Morphology, samples: int = 3000, margin: float = MARGIN, seed: int = 0,
                           slack: float = 0.0) -> frozenset:
    """Node pairs (not parent-child) that come within `margin` in at least one of `samples` uniform random poses
    within the joint ranges (widened by `slack`), posed by MuJoCo's own `mj_kinematics`: a lower bound on the pairs
    that can touch, used to check the cut and to measure how tight it is."""
    mm = compile_model(m)
    kin = kinematics(mm)
    d = mujoco.MjData(mm)
    rng = np.random.default_rng(seed)
    q = kin.joint_lo - slack + rng.random((samples, kin.num_joints)) * (kin.joint_hi - kin.joint_lo + 2 * slack)
    ends = np.zeros((samples, kin.num_nodes, 2, 3))
    geom = mm.body_geomadr[1:]
    half = np.where(mm.geom_type[geom] == mujoco.mjtGeom.mjGEOM_CAPSULE, mm.geom_size[geom, 1], 0.0)
    for i in range(samples):
        d.qpos[:] = 0.0
        d.qpos[3] = 1.0
        d.qpos[7:] = q[i]
        mujoco.mj_kinematics(mm, d)
        axis = d.geom_xmat[geom].reshape(-1, 3, 3)[:, :, 2] * half[:, None]
        ends[i, :, 0] = d.geom_xpos[geom] - axis
        ends[i, :, 1] = d.geom_xpos[geom] + axis
    out = set()
    for a, b in candidate_node_pairs(kin):
        dist = segment_distance(ends[:, a, 0], ends[:, a, 1], ends[:, b, 0], ends[:, b, 1])
        if np.any(dist - kin.radius[a] - kin.radius[b] <= margin):
            out.add((a, b))
    return frozenset(out)


# ---- a robot set on its shared tree -------------------------------------------------------------------------------
def slot_pair(tree: SharedTree, robot: int, a: int, b: int) -> tuple[int, int]:
    """The slot pair of node pair (a, b) of robot `robot` of the tree's set."""
    slot = lambda n: 0 if n == 0 else tree.slot_of[robot][n - 1]
    s, t = slot(a), slot(b)
    return (s, t) if s < t else (t, s)


def candidate_slot_pairs(tree: SharedTree) -> frozenset:
    """Slot pairs that are not parent-child: MJX's self-collision pairs without a cut."""
    S = tree.num_slots
    return frozenset((s, t) for s in range(S) for t in range(s + 1, S) if tree.parent[t] != s)


def used_slot_pairs(robots: Sequence[Morphology], tree: SharedTree) -> frozenset:
    """Candidate slot pairs whose two slots are both used by some robot."""
    out = set()
    for r, m in enumerate(robots):
        used = [0, *tree.slot_of[r]]
        out.update((min(s, t), max(s, t)) for i, s in enumerate(used) for t in used[i + 1:])
    return frozenset(out) & candidate_slot_pairs(tree)


@dataclasses.dataclass(frozen=True)
class SlotPairs:
    """The cut of a robot set on its shared tree."""
    kept: frozenset       # slot pairs (s, t), s < t, that some robot using both slots can make touch (or unproved)
    touching: frozenset   # ... of which some robot was shown to make them touch (a pose with f <= margin)
    unresolved: int       # robot geom pairs kept only because the box budget ran out, summed over the robots
    seconds: float        # time the search took (robots already cached take none)


def find_slot_pairs(robots: Sequence[Morphology], tree: SharedTree, margin: float = MARGIN, slack: float = SLACK,
                    budget: int = BOX_BUDGET) -> SlotPairs:
    """The cut of the set: every robot's node pairs (`robot_pairs`) mapped onto the tree's slots."""
    t0 = time.perf_counter()
    kept, touching, unresolved = set(), set(), 0
    for r, found in enumerate(robots_pairs(robots, margin, slack, budget)):
        kept.update(slot_pair(tree, r, a, b) for a, b in found.kept)
        touching.update(slot_pair(tree, r, a, b) for a, b in found.touching)
        unresolved += len(found.unresolved)
    return SlotPairs(frozenset(kept), frozenset(touching), unresolved, time.perf_counter() - t0)


def touching_slot_pairs(robots: Sequence[Morphology], tree: SharedTree, margin: float = MARGIN,
                        slack: float = SLACK, budget: int = BOX_BUDGET) -> frozenset:
    """Slot pairs (s, t), s < t, kept by the cut: some robot of the set uses both slots and its two geoms there can
    come within `margin` (or were not proved apart within the budget)."""
    return find_slot_pairs(robots, tree, margin, slack, budget).kept


# ---- what MJX allocates -------------------------------------------------------------------------------------------
_GEOM_NAMES = {int(v): k.removeprefix("mjGEOM_").lower() for k, v in mujoco.mjtGeom.__members__.items()}


def mjx_pair_counts(mm: mujoco.MjModel) -> dict[str, int]:
    """MJX's static candidate geom pairs of a compiled model, counted by geom types ("capsule-capsule": n, ...)."""
    from mujoco.mjx._src import collision_driver
    out: dict[str, int] = {}
    for g1, g2, _ in collision_driver.geom_pairs(mm):
        key = f"{_GEOM_NAMES[int(mm.geom_type[g1])]}-{_GEOM_NAMES[int(mm.geom_type[g2])]}"
        out[key] = out.get(key, 0) + 1
    return dict(sorted(out.items()))


def mjx_contact_count(mm: mujoco.MjModel) -> int:
    """Contacts MJX allocates per env for a compiled model (one per contact point of every candidate pair)."""
    from mujoco.mjx._src import collision_driver
    return int(len(collision_driver.make_condim(mm)))


@dataclasses.dataclass(frozen=True)
class SelfPairSummary:
    """The self-collision pairs of a stacked model.

    candidates   slot pairs MJX checks with self-collision on and no cut (all pairs that are not parent-child)
    used         ... of which some robot uses both slots
    kept         slot pairs MJX checks: after the cut, all candidates without it, 0 with self-collision off
    touching     ... of which some robot was shown to make them touch (None when the cut was not searched here)
    unresolved   robot geom pairs kept only because the search ran out of budget (summed over robots)
    seconds      time the search took
    mjx_pairs    MJX's candidate geom pairs of one compiled padded robot by geom types, terrain pairs included
                 (the same for every robot of the set)
    mjx_contacts contacts MJX allocates per env (ncon of every candidate pair's collision function)
    budget       limb-limb pairs MJX collides per env (the closest; None: all), `SolverOptions.self_pair_budget`
    """
    self_collision: bool
    cut: bool
    num_slots: int
    candidates: int
    used: int
    kept: int
    touching: int | None
    unresolved: int
    seconds: float
    mjx_pairs: tuple[tuple[str, int], ...]
    mjx_contacts: int
    budget: int | None = None

    def line(self) -> str:
        """One line for the logs, e.g. "self-collision pairs: kept 144 of 325 candidates (193 used by some robot,
        142 shown to touch), found in 13.7 s; MJX pairs: capsule-capsule 120, ...; 196 contacts per env"."""
        if not self.self_collision:
            head = "self-collision off"
        elif not self.cut:
            head = (f"self-collision pairs: kept {self.kept} of {self.candidates} candidates "
                    f"({self.used} used by some robot), no cut")
        else:
            shown = "" if self.touching is None else f", {self.touching} shown to touch"
            head = (f"self-collision pairs: kept {self.kept} of {self.candidates} candidates "
                    f"({self.used} used by some robot{shown}), found in {self.seconds:.1f} s")
        pairs = ", ".join(f"{k} {v}" for k, v in self.mjx_pairs)
        budget = "" if self.budget is None else f" (limb pairs culled to the {self.budget} closest)"
        return f"{head}; MJX pairs: {pairs}; {self.mjx_contacts} contacts per env{budget}"


def summarise(robots: Sequence[Morphology], tree: SharedTree, self_collision: bool, kept: frozenset | None,
              mm: mujoco.MjModel, search: SlotPairs | None = None) -> SelfPairSummary:
    """The summary of a stacked model: `kept` the slot pairs left by the cut (None: no cut), `mm` one compiled
    padded robot, `search` the cut's search when it was run for this model."""
    cands = candidate_slot_pairs(tree)
    cut = self_collision and kept is not None
    return SelfPairSummary(
        self_collision=self_collision, cut=cut, num_slots=tree.num_slots, candidates=len(cands),
        used=len(used_slot_pairs(robots, tree)),
        kept=0 if not self_collision else len(kept) if cut else len(cands),
        touching=len(search.touching) if cut and search is not None else None,
        unresolved=search.unresolved if cut and search is not None else 0,
        seconds=search.seconds if cut and search is not None else 0.0,
        mjx_pairs=tuple(mjx_pair_counts(mm).items()), mjx_contacts=mjx_contact_count(mm))
