"""Generate new UNIMAL robots: DERL's design space and mutation operators, rebuilt from spec/unimal.md §3-4.

A robot is a sphere torso (r = 0.1) with a tree of capsule limbs (r = 0.05). Every limb hangs at a growth site
of its parent (the torso centre, or a limb's `mid` / `btm` site) in one of 24 directions (θ in 0°, 45°, ..., 315°
from +x, φ in 90°, 135°, 180° from +z), with a length parameter h in {0.2, 0.3, 0.4}:

- body pos = site + v(p_r, θ, φ) (p_r = 0.1 on the torso, 0.05 on a limb), capsule `fromto` = 0 → v(r + h, θ, φ),
  joint pos = v(r, θ + 180°, 180° - φ), sites mid = v(r + h/2), btm = v(r + h), btm_pos = v(2r + h), where
  v(ρ, θ, φ) = ρ (sin φ cos θ, sin φ sin θ, cos φ) with every component rounded to 2 decimals (`sph2cart`);
  positions are plain float sums of such rounded vectors, as DERL writes them;
- 1 or 2 hinges per limb, DoF set x / y / xy; the axes are the x / y columns of MuJoCo's `fromto` frame of the
  capsule (z = unit(from - to)), rounded to 4 decimals; ranges from the 13 DERL intervals, gears {150..300};
- one torso density and one limb density per robot, each from {500, 600, ..., 1000}.

`grow_limb` adds one limb, or a mirror pair: two limbs on one plane site ((θ, φ) and (360° - θ, φ)) or one on
each site of a mirror-site pair (same (θ, φ)). A growth is kept only if the robot stays bilaterally symmetric and
no new self-contact appears. The other mutation operators are `joint_angle`, `gear`, `dof` (½: every limb group,
½: one group; a mirror pair is one group and gets identical values), `limb_params` (one group gets a new h;
the group's capsules and its children's positions are recomputed), `density` and `delete_limb` (one leaf group).

Decisions where the spec leaves room (ours, not DERL's):
- Symmetry test: MuJoCo's centre of mass of the torso subtree at the rest pose (`mj_forward`, torso at the origin)
  must have |y| <= `SYMMETRY_TOL` = 1e-9 m. DERL compares with exact float equality after one `mj_step`, which
  also rejects mirror-image robots whose float sums do not cancel exactly; a mirror-image robot gives
  |y| ~ 1e-17 here, a real asymmetry >= ~1e-3 m. A cheap structural mirror test (world positions of every pair
  mirror each other, unpaired limbs lie in the xz plane) runs first and skips the compile when it fails.
- Self-contact: `mj_forward` contacts of the compiled robot (parent-child pairs filtered) that overlap by more
  than `CONTACT_TOL` = 1e-6 m. Capsules touching exactly (distance 0 up to float noise) are common on this grid,
  e.g. two limbs leaving one site in opposite directions (-x and +x); MuJoCo reports them or not depending on
  ~1e-17 m of noise, and the originals are full of them (54 of 202 robots), so they do not count, on every machine.
  Allowed: the two limbs of a same-site pair. `grow_limb` and `limb_params` may add no other contact. A robot
  passed to `mutate` that already has other contacts (one original robot does) keeps them.
- Directions: DERL samples 24 (θ, φ); the originals show only 13 directions (spec §3.1). The missing 3-d
  diagonals (θ = 45°, 135°, ... with φ = 135°) can only appear as mirror pairs, and for those DERL's 2-decimal
  rounding hits exact ties (0.35 · ½ = 0.175) that numpy's sin/cos resolve differently for θ and 360° - θ, so
  the symmetry test rejected them (by float noise). We compute `sph2cart` from exact cos/sin values (the same
  bits on every machine) and reject the 3-d diagonals explicitly, which gives exactly the 13 directions.
- Besides DERL's rule "no limb along its parent's direction at the parent's `mid` site", we also reject a limb
  pointing straight back along its parent (it would lie inside the parent; parent-child contacts are ignored,
  so the contact test cannot see it). None of the 202 original robots has one.
- Standing height (`set_head_pos`): torso at the origin, lowest `btm_pos` point z_min over the torso's
  (0, 0, -0.1) and every limb's v(2r + h) at the rest pose (computed kinematically: bodies are never rotated, so
  this equals `mj_forward`; one `mj_step` would lower everything by ~2.5e-4 m, which never changes the result after
  rounding because z_min is a multiple of 0.01), height = round(-z_min + 0.2, 2). We use DERL's creation-time
  btm_pos v(2r + h) also after `limb_params` (DERL's bug writes v(r + h) there, spec §3.2).
- New limb ids are max(id) + 1 (DERL keeps a counter that never reuses deleted ids; ids only need to be unique).
- Population init (spec §4.1): one `grow_limb`, then random operators until the robot has >= target limbs. DERL
  draws the target from {2..8}; our default `DEFAULT_NUM_LIMBS` = (6, 10) gives limb counts comparable to the
  original train set (4-10 limbs, mean 8.1, mode 8; generated with the height cap below: 6-10, mean 7.9; a pair
  can overshoot the target by one). Random operator choice as in DERL: uniform over the 7 operators, no grow at 10 limbs, no delete at <= 2
  limbs, only grow at 0 limbs.
- Height cap (a selection of ours, like evolution's): unselected random robots are taller than the evolved
  originals (measured on 100: standing height 0.55-2.45 m, median 1.14, tree depth 2-6; originals 0.30-1.04 m,
  depth 2-5), so by default a robot whose standing height exceeds `DEFAULT_MAX_HEIGHT` = 1.05 m is drawn again
  (about 40 % are kept). This keeps the depth at 2-5, and slightly favours smaller robots (mean 7.9 limbs with the
  cap, 8.5 without). `max_height=None` gives DERL's unselected distribution.
- When an operator cannot be applied (grow at 10 limbs or no valid growth in `ATTEMPTS` tries, delete with
  <= 2 limbs, no contact-free `limb_params` in `ATTEMPTS` tries) `mutate` returns the robot unchanged.
- The limb geometry of an existing robot (θ, φ, h and attachment site of every limb) is read back from its
  `tip` and `pos`; this works for all 202 original robots. A robot outside this geometry raises `RobotError`.
"""
from __future__ import annotations

import dataclasses
from typing import Iterable, Sequence

import mujoco
import numpy as np

from .errors import RobotError
from .mjcf import compile_model
from .morphology import LIMB_RADIUS, MAX_LIMBS, TORSO, TORSO_RADIUS, Joint, Limb, Morphology

# ---- the design space (DERL config values, spec §3.4) ---------------------------------------------------------
THETAS = tuple(float(t) for t in range(0, 360, 45))   # degrees from +x
PHIS = (90.0, 135.0, 180.0)                           # degrees from +z: horizontal, 45° down, straight down
LIMB_HEIGHTS = (0.2, 0.3, 0.4)                        # h; the capsule segment is r + h long
DOF_SETS = ("x", "y", "xy")
JOINT_RANGES = tuple((float(a), float(b)) for a, b in (
    (-30, 0), (0, 30), (-30, 30), (-45, 45), (-45, 0), (0, 45), (-60, 0), (0, 60), (-60, 60), (-90, 0), (0, 90),
    (-60, 30), (-30, 60)))
GEARS = (150.0, 200.0, 250.0, 300.0)
DENSITIES = (500.0, 600.0, 700.0, 800.0, 900.0, 1000.0)
FLOOR_OFFSET = 0.2
MUTATION_OPS = ("grow_limb", "joint_angle", "limb_params", "dof", "density", "gear", "delete_limb")
ATTEMPTS = 50                      # DERL's grow_limb tries; also used for limb_params
SYMMETRY_TOL = 1e-9                # metres, |y| of the centre of mass
CONTACT_TOL = 1e-6                 # metres: a contact needs more overlap than this (exact touching does not count)
DEFAULT_NUM_LIMBS = (6, 10)        # target limb count drawn uniformly from this closed range
DEFAULT_MAX_HEIGHT = 1.05          # standing height cap (m); None = no cap
MAX_OPS = 2000                     # random operators per robot before starting again

_SITES = ("mid", "btm")
_R = LIMB_RADIUS


# cos and sin of multiples of 45°, so that `sph2cart` uses only IEEE-exact operations and gives the same bits on
# every machine (numpy's sin/cos may differ by an ulp between CPUs, which flips 2-decimal rounding ties)
_H = float(np.sqrt(0.5))
_COS_SIN = {0: (1.0, 0.0), 45: (_H, _H), 90: (0.0, 1.0), 135: (-_H, _H), 180: (-1.0, 0.0), 225: (-_H, -_H),
            270: (0.0, -1.0), 315: (_H, -_H)}


def _cos_sin(angle: float) -> tuple[float, float]:
    a = int(round(angle)) % 360
    if a not in _COS_SIN or abs(angle - round(angle)) > 1e-9:
        raise ValueError(f"angle {angle}: the UNIMAL design space uses multiples of 45 degrees")
    return _COS_SIN[a]


def sph2cart(r: float, theta: float, phi: float) -> tuple[float, float, float]:
    """DERL's spherical helper: r (sin φ cos θ, sin φ sin θ, cos φ), angles in degrees (multiples of 45°), each
    component rounded to 2 decimals, -0.0 turned into 0.0."""
    ct, st = _cos_sin(theta)
    cp, sp = _cos_sin(phi)
    v = np.round(np.array([r * sp * ct, r * sp * st, r * cp]), 2) + 0.0
    return (float(v[0]), float(v[1]), float(v[2]))


def _add(a: Sequence[float], b: Sequence[float]) -> tuple[float, float, float]:
    return (float(a[0] + b[0]), float(a[1] + b[1]), float(a[2] + b[2]))


def joint_axes(tip: Sequence[float]) -> dict[str, tuple[float, float, float]]:
    """Joint axes "x"/"y" of a capsule `fromto="0 0 0 tip"`: the x/y columns of MuJoCo's geom frame (z axis
    = unit(from - to), minimal rotation from +z), rounded to 4 decimals, as DERL writes them."""
    z = -np.asarray(tip, dtype=float)
    z = z / np.linalg.norm(z)
    quat = np.zeros(4)
    mujoco.mju_quatZ2Vec(quat, z)
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, quat)
    mat = np.round(mat.reshape(3, 3), 4) + 0.0
    return {"x": tuple(float(v) for v in mat[:, 0]), "y": tuple(float(v) for v in mat[:, 1])}


def joint_pos(theta: float, phi: float) -> tuple[float, float, float]:
    """Joint position in the limb's body frame: on the proximal tip of the capsule (spec §3.2)."""
    return sph2cart(_R, theta + 180.0, 180.0 - phi)


# tip (rounded) -> (theta, phi, h); phi = 180° gives the same tip for every theta: keep theta = 0
_TIP_TABLE: dict[tuple[float, float, float], tuple[float, float, float]] = {}
for _h in LIMB_HEIGHTS:
    for _p in PHIS:
        for _t in THETAS:
            _TIP_TABLE.setdefault(sph2cart(_R + _h, _t, _p), (_t, _p, _h))


def _tip_key(tip: Sequence[float]) -> tuple[float, float, float]:
    return tuple(round(float(x), 2) + 0.0 for x in tip)


def _unit(theta: float, phi: float) -> np.ndarray:
    ct, st = _cos_sin(theta)
    cp, sp = _cos_sin(phi)
    return np.array([sp * ct, sp * st, cp])


# ---- a mutable working copy of a robot ------------------------------------------------------------------------
@dataclasses.dataclass
class _Node:
    limb: Limb                 # `limb.parent` is stale here; `parent` holds the parent's limb id
    parent: int | None         # parent limb id, None for the torso
    site: str                  # "torso", "mid" or "btm" (of the parent)
    theta: float
    phi: float
    h: float


@dataclasses.dataclass
class _Draft:
    name: str
    height: float
    torso_density: float
    torso_radius: float
    limb_density: float
    nodes: list[_Node]         # sibling order = order in this list
    pairs: list[tuple[int, int]]

    def copy(self) -> "_Draft":
        return dataclasses.replace(self, nodes=[dataclasses.replace(n) for n in self.nodes], pairs=list(self.pairs))

    def node(self, limb_id: int) -> _Node:
        for n in self.nodes:
            if n.limb.id == limb_id:
                return n
        raise KeyError(limb_id)

    def children(self, limb_id: int | None) -> list[_Node]:
        return [n for n in self.nodes if n.parent == limb_id]

    def dfs(self) -> list[_Node]:
        out: list[_Node] = []

        def visit(pid: int | None) -> None:
            for c in self.children(pid):
                out.append(c)
                visit(c.limb.id)
        visit(None)
        return out

    def partner(self, limb_id: int) -> int | None:
        for a, b in self.pairs:
            if a == limb_id:
                return b
            if b == limb_id:
                return a
        return None

    def groups(self) -> list[tuple[int, ...]]:
        """Limb groups in body order: a mirror pair is one group, every other limb its own group."""
        seen: set[int] = set()
        out: list[tuple[int, ...]] = []
        for n in self.dfs():
            lid = n.limb.id
            if lid in seen:
                continue
            p = self.partner(lid)
            g = (lid,) if p is None else tuple(sorted((lid, p)))
            seen.update(g)
            out.append(g)
        return out

    def site_pos(self, parent: int | None, site: str) -> tuple[float, float, float]:
        if parent is None:
            return (0.0, 0.0, 0.0)
        n = self.node(parent)
        return sph2cart(_R + (n.h / 2 if site == "mid" else n.h), n.theta, n.phi)

    def limb_pos(self, parent: int | None, site: str, theta: float, phi: float) -> tuple[float, float, float]:
        p_r = self.torso_radius if parent is None else _R
        return _add(self.site_pos(parent, site), sph2cart(p_r, theta, phi))

    def to_morphology(self) -> Morphology:
        order = self.dfs()
        index = {n.limb.id: i for i, n in enumerate(order)}
        limbs = tuple(dataclasses.replace(n.limb, parent=TORSO if n.parent is None else index[n.parent])
                      for n in order)
        pairs = tuple((int(a), int(b)) for a, b in self.pairs)
        return Morphology(name=self.name, height=float(self.height), limbs=limbs,
                          torso_density=float(self.torso_density), torso_radius=float(self.torso_radius),
                          mirror_pairs=pairs)

    def world(self) -> dict[int, np.ndarray]:
        """Rest-pose world positions of the limb origins, torso at the origin."""
        out: dict[int, np.ndarray] = {}
        for n in self.dfs():
            base = np.zeros(3) if n.parent is None else out[n.parent]
            out[n.limb.id] = base + np.asarray(n.limb.pos)
        return out

    def standing_height(self) -> float:
        world = self.world()
        zmin = -self.torso_radius
        for n in self.nodes:
            zmin = min(zmin, world[n.limb.id][2] + sph2cart(2 * _R + n.h, n.theta, n.phi)[2])
        return float(np.round(-zmin + FLOOR_OFFSET, 2))

    def same_site_pairs(self) -> set[frozenset[str]]:
        out = set()
        for a, b in self.pairs:
            na, nb = self.node(a), self.node(b)
            if na.parent == nb.parent and na.site == nb.site:
                out.add(frozenset((na.limb.name, nb.limb.name)))
        return out


def _draft(m: Morphology) -> _Draft:
    """Working copy of a robot, with the DERL geometry of every limb read back from `tip` and `pos`."""
    nodes: list[_Node] = []
    ids: list[int] = []
    d = _Draft(m.name, m.height, m.torso_density, m.torso_radius,
               m.limbs[0].density if m.limbs else DENSITIES[-1], nodes, [tuple(p) for p in m.mirror_pairs])
    for l in m.limbs:
        geo = _TIP_TABLE.get(_tip_key(l.tip))
        if geo is None or abs(l.radius - _R) > 1e-9:
            raise RobotError(m.name, f'<body name="{l.name}">',
                             f"capsule fromto 0 -> {tuple(l.tip)} radius {l.radius} is not a UNIMAL generator limb "
                             f"(expected v(0.05 + h, θ, φ), h in {LIMB_HEIGHTS}, radius 0.05)")
        theta, phi, h = geo
        parent = None if l.parent == TORSO else ids[l.parent]
        sites = ("torso",) if parent is None else _SITES
        site = None
        for s in sites:
            if np.allclose(l.pos, d.limb_pos(parent, s, theta, phi), atol=1e-6):
                site = s
                break
        if site is None:
            raise RobotError(m.name, f'<body name="{l.name}">',
                             f"pos {tuple(l.pos)} is not at a growth site of its parent "
                             f"(expected site + v(p_r, θ, φ) at the torso centre or the parent's mid/btm site)")
        nodes.append(_Node(l, parent, site, theta, phi, h))
        ids.append(l.id)
    return d


# ---- checks ---------------------------------------------------------------------------------------------------
def _mirror_ok(d: _Draft) -> bool:
    """Structural bilateral symmetry: pairs are mirror images in the xz plane, other limbs lie in it."""
    world = d.world()
    paired = set()
    for a, b in d.pairs:
        paired.update((a, b))
        na, nb = d.node(a), d.node(b)
        s = np.array([1.0, -1.0, 1.0])
        if not (np.allclose(world[b], s * world[a], atol=1e-9) and np.allclose(nb.limb.tip, s * np.asarray(na.limb.tip), atol=1e-9)):
            return False
    for n in d.nodes:
        if n.limb.id not in paired and (abs(world[n.limb.id][1]) > 1e-9 or abs(n.limb.tip[1]) > 1e-9):
            return False
    return True


def robot_physics(m: Morphology) -> tuple[float, set[frozenset[str]]]:
    """(y of the centre of mass, set of touching body-name pairs) at the rest pose, from MuJoCo `mj_forward` on the
    compiled robot without a floor; only geoms overlapping by more than `CONTACT_TOL` count. Parent-child pairs
    are left out."""
    model = compile_model(m)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    torso = model.body("torso/0").id
    contacts: set[frozenset[str]] = set()
    geoms = np.asarray(data.contact.geom).reshape(-1, 2)[: data.ncon]
    dists = np.asarray(data.contact.dist).reshape(-1)[: data.ncon]
    for (g1, g2), dist in zip(geoms, dists):
        if dist > -CONTACT_TOL:
            continue
        b1, b2 = int(model.geom_bodyid[g1]), int(model.geom_bodyid[g2])
        if b1 == b2 or model.body_parentid[b1] == b2 or model.body_parentid[b2] == b1:
            continue
        contacts.add(frozenset((model.body(b1).name, model.body(b2).name)))
    return float(data.subtree_com[torso][1]), contacts


def _physics_ok(d: _Draft, base_contacts: set[frozenset[str]]) -> bool:
    """Symmetric centre of mass, and no contacts beyond `base_contacts` and the same-site pairs."""
    com_y, contacts = robot_physics(d.to_morphology())
    return abs(com_y) <= SYMMETRY_TOL and not (contacts - base_contacts - d.same_site_pairs())


def _direction_ok(d: _Draft, parent: int | None, site: str, theta: float, phi: float) -> bool:
    if phi == 135.0 and int(round(theta)) % 90 == 45:   # a 3-d diagonal (see the module notes)
        return False
    if parent is None:
        return True
    p = d.node(parent)
    c = float(np.dot(_unit(theta, phi), _unit(p.theta, p.phi)))
    if c < -1 + 1e-9:                      # straight back into the parent
        return False
    return not (site == "mid" and c > 1 - 1e-9)


# ---- sampling helpers -----------------------------------------------------------------------------------------
def _pick(rng: np.random.Generator, seq: Sequence, exclude=None):
    options = [v for v in seq if v != exclude] if exclude is not None else list(seq)
    return options[int(rng.integers(len(options)))]


def _make_joints(dof: str, theta: float, phi: float, tip, params: dict[str, tuple[tuple[float, float], float]],
                 like: Joint | None = None) -> tuple[Joint, ...]:
    axes = joint_axes(tip)
    jp = joint_pos(theta, phi)
    extra = {} if like is None else dict(armature=like.armature, damping=like.damping, stiffness=like.stiffness)
    return tuple(Joint(kind=k, pos=jp, axis=axes[k], range=params[k][0], gear=params[k][1], **extra) for k in dof)


def _sample_params(rng: np.random.Generator, dof: str) -> dict[str, tuple[tuple[float, float], float]]:
    return {k: (_pick(rng, JOINT_RANGES), _pick(rng, GEARS)) for k in dof}


# ---- operators on drafts (return True when the draft changed) -------------------------------------------------
def _grow(d: _Draft, rng: np.random.Generator) -> bool:
    n_limbs = len(d.nodes)
    if n_limbs >= MAX_LIMBS:
        return False
    base_contacts = robot_physics(d.to_morphology())[1] if d.nodes else set()
    sites: list[tuple[int | None, str]] = [(None, "torso")] + [(n.limb.id, s) for n in d.dfs() for s in _SITES]
    for _ in range(ATTEMPTS):
        parent, site = sites[int(rng.integers(len(sites)))]
        mirror = None if parent is None else d.partner(parent)
        count = 2 if mirror is not None else int(rng.integers(1, 3))
        if n_limbs + count > MAX_LIMBS:
            continue
        h = _pick(rng, LIMB_HEIGHTS)
        dof = _pick(rng, DOF_SETS)
        params = _sample_params(rng, dof)
        theta, phi = _pick(rng, THETAS), _pick(rng, PHIS)
        if count == 2 and theta > 180:
            theta = 360.0 - theta
        if mirror is not None:
            first, second = sorted((parent, mirror), key=lambda i: f"limb/{site}/{i}")
            places = [(first, theta), (second, theta)]
        elif count == 2:
            if theta in (0.0, 180.0) or phi == 180.0:
                continue
            places = [(parent, theta), (parent, 360.0 - theta)]
        else:
            places = [(parent, theta)]
        if not all(_direction_ok(d, p, site, t, phi) for p, t in places):
            continue
        new_id = max((n.limb.id for n in d.nodes), default=-1) + 1
        cand = d.copy()
        for k, (p, t) in enumerate(places):
            tip = sph2cart(_R + h, t, phi)
            limb = Limb(id=new_id + k, parent=TORSO, pos=cand.limb_pos(p, site, t, phi), tip=tip,
                        joints=_make_joints(dof, t, phi, tip, params), radius=_R, density=d.limb_density)
            cand.nodes.append(_Node(limb, p, site, t, phi, h))
        if count == 2:
            cand.pairs.append((new_id, new_id + 1))
        if not _mirror_ok(cand):
            continue
        if not _physics_ok(cand, base_contacts):
            continue
        cand.height = cand.standing_height()
        d.nodes, d.pairs, d.height = cand.nodes, cand.pairs, cand.height
        return True
    return False


def _chosen_groups(d: _Draft, rng: np.random.Generator) -> list[tuple[int, ...]]:
    groups = d.groups()
    if rng.random() < 0.5:
        return groups
    return [groups[int(rng.integers(len(groups)))]]


def _joint_values(d: _Draft, rng: np.random.Generator, attr: str, values: Sequence, force: bool) -> bool:
    """`joint_angle` (attr "range") and `gear` (attr "gear")."""
    if not d.nodes:
        return False
    for g in _chosen_groups(d, rng):
        first = d.node(g[0]).limb
        new = {j.kind: _pick(rng, values, getattr(j, attr) if force else None) for j in first.joints}
        for lid in g:
            n = d.node(lid)
            n.limb = dataclasses.replace(n.limb, joints=tuple(
                dataclasses.replace(j, **{attr: new.get(j.kind, getattr(j, attr))}) for j in n.limb.joints))
    return True


def _dof(d: _Draft, rng: np.random.Generator, force: bool) -> bool:
    if not d.nodes:
        return False
    for g in _chosen_groups(d, rng):
        first = d.node(g[0]).limb
        current = "".join(j.kind for j in first.joints)
        dof = _pick(rng, DOF_SETS, current if force else None)
        params = _sample_params(rng, dof)
        for lid in g:
            n = d.node(lid)
            n.limb = dataclasses.replace(n.limb, joints=_make_joints(dof, n.theta, n.phi, n.limb.tip, params,
                                                                     like=n.limb.joints[0]))
    return True


def _density(d: _Draft, rng: np.random.Generator, force: bool) -> bool:
    d.torso_density = _pick(rng, DENSITIES, d.torso_density if force else None)
    d.limb_density = _pick(rng, DENSITIES, d.limb_density if force else None)
    for n in d.nodes:
        n.limb = dataclasses.replace(n.limb, density=d.limb_density)
    return True


def _set_h(d: _Draft, group: Iterable[int], h: float) -> None:
    for lid in group:
        n = d.node(lid)
        n.h = h
        n.limb = dataclasses.replace(n.limb, tip=sph2cart(_R + h, n.theta, n.phi))
        for c in d.children(lid):
            c.limb = dataclasses.replace(c.limb, pos=d.limb_pos(lid, c.site, c.theta, c.phi))


def _limb_params(d: _Draft, rng: np.random.Generator, force: bool) -> bool:
    if not d.nodes:
        return False
    base_contacts = robot_physics(d.to_morphology())[1]
    groups = d.groups()
    for _ in range(ATTEMPTS):
        g = groups[int(rng.integers(len(groups)))]
        h = _pick(rng, LIMB_HEIGHTS, d.node(g[0]).h if force else None)
        cand = d.copy()
        _set_h(cand, g, h)
        if not _mirror_ok(cand) or not _physics_ok(cand, base_contacts):
            continue
        cand.height = cand.standing_height()
        d.nodes, d.height = cand.nodes, cand.height
        return True
    return False


def _delete(d: _Draft, rng: np.random.Generator) -> bool:
    if len(d.nodes) <= 2:
        return False
    leaves = [g for g in d.groups() if all(not d.children(lid) for lid in g)]
    g = set(leaves[int(rng.integers(len(leaves)))])
    d.nodes = [n for n in d.nodes if n.limb.id not in g]
    d.pairs = [p for p in d.pairs if p[0] not in g and p[1] not in g]
    d.height = d.standing_height()
    return True


def _apply(d: _Draft, op: str, rng: np.random.Generator, force: bool = False) -> bool:
    if op == "grow_limb":
        return _grow(d, rng)
    if op == "joint_angle":
        return _joint_values(d, rng, "range", JOINT_RANGES, force)
    if op == "gear":
        return _joint_values(d, rng, "gear", GEARS, force)
    if op == "dof":
        return _dof(d, rng, force)
    if op == "density":
        return _density(d, rng, force)
    if op == "limb_params":
        return _limb_params(d, rng, force)
    if op == "delete_limb":
        return _delete(d, rng)
    raise ValueError(f"unknown mutation {op!r}; expected one of {MUTATION_OPS}")


def _random_op(d: _Draft, rng: np.random.Generator) -> str:
    n = len(d.nodes)
    if n == 0:
        return "grow_limb"
    ops = [o for o in MUTATION_OPS if not (o == "grow_limb" and n >= MAX_LIMBS) and not (o == "delete_limb" and n <= 2)]
    return ops[int(rng.integers(len(ops)))]


# ---- public API -----------------------------------------------------------------------------------------------
def _rng(rng_or_seed) -> np.random.Generator:
    if isinstance(rng_or_seed, np.random.Generator):
        return rng_or_seed
    return np.random.default_rng(rng_or_seed)


def mutate(m: Morphology, op: str, rng, *, force_change: bool = False) -> Morphology:
    """Apply one DERL mutation operator (one of `MUTATION_OPS`) and return the new robot (same name).

    Returns `m` itself when the operator cannot be applied (see the module notes). With `force_change`, every
    value the operator re-draws differs from the current one (used by the variants); DERL re-draws freely."""
    if op not in MUTATION_OPS:
        raise ValueError(f"unknown mutation {op!r}; expected one of {MUTATION_OPS}")
    d = _draft(m)
    if not _apply(d, op, _rng(rng), force_change):
        return m
    return d.to_morphology()


def generate_robot(rng_or_seed, name: str, num_limbs: tuple[int, int] = DEFAULT_NUM_LIMBS,
                   max_height: float | None = DEFAULT_MAX_HEIGHT, max_ops: int = MAX_OPS) -> Morphology:
    """One new robot (DERL population init): draw densities and a target limb count uniformly from the closed
    range `num_limbs`, grow one limb, then apply random mutation operators until the robot has at least that many
    limbs. A robot taller than `max_height` (standing height, m; None = no cap) is drawn again from the same
    stream. `rng_or_seed` is a `numpy.random.Generator` or anything `numpy.random.default_rng` accepts."""
    lo, hi = num_limbs
    if not 1 <= lo <= hi <= MAX_LIMBS:
        raise ValueError(f"num_limbs={num_limbs}: expected 1 <= lo <= hi <= {MAX_LIMBS}")
    rng = _rng(rng_or_seed)
    for _ in range(100):
        d = _Draft(name, 0.0, _pick(rng, DENSITIES), TORSO_RADIUS, _pick(rng, DENSITIES), [], [])
        target = int(rng.integers(lo, hi + 1))
        for _ in range(max_ops):
            if len(d.nodes) >= target:
                break
            _apply(d, _random_op(d, rng), rng)
        else:
            continue
        if max_height is None or d.height <= max_height + 1e-9:
            return d.to_morphology()
    raise RobotError(name, "", f"could not grow a robot with {num_limbs} limbs and height <= {max_height}")


def generate_set(num: int, seed: int, *, num_limbs: tuple[int, int] = DEFAULT_NUM_LIMBS,
                 max_height: float | None = DEFAULT_MAX_HEIGHT,
                 exclude_topologies: Iterable[str] | None = None, prefix: str = "gen") -> list[Morphology]:
    """`num` robots named `<prefix>-<seed>-<index>`. Robot `index` is drawn from `default_rng([seed, index, a])`
    for a = 0, 1, ... until its `topology_key` is not in `exclude_topologies`, so a robot does not depend on
    the others and the same arguments always give the same robots."""
    exclude = set(exclude_topologies or ())
    out = []
    for index in range(num):
        for attempt in range(10_000):
            m = generate_robot(np.random.default_rng([seed, index, attempt]), f"{prefix}-{seed}-{index}", num_limbs,
                               max_height)
            if topology_key(m) not in exclude:
                break
        else:
            raise RobotError(f"{prefix}-{seed}-{index}", "", "every topology drawn is excluded")
        out.append(m)
    return out


def topology_key(m: Morphology) -> str:
    """Canonical key of the limb tree's shape, independent of child order, ids and geometry: each node is
    "(" + its children's keys sorted + ")", starting from the torso. E.g. a torso with two bare limbs: "(()())"."""
    def key(index: int) -> str:
        return "(" + "".join(sorted(key(c) for c in m.children(index))) + ")"
    return key(TORSO)


def limb_geometry(m: Morphology) -> list[dict]:
    """Per limb (body order): DERL's θ, φ (degrees), h, and the attachment site ("torso", "mid" or "btm")."""
    return [dict(theta=n.theta, phi=n.phi, h=n.h, site=n.site) for n in _draft(m).nodes]


def standing_height(m: Morphology) -> float:
    """DERL's `set_head_pos` height for the robot's geometry (see the module notes)."""
    return _draft(m).standing_height()


def check_design_space(m: Morphology, *, contacts: bool = True, height: bool = True,
                       dynamics: bool = True) -> list[str]:
    """Problems of a robot w.r.t. the generator's design space (empty when inside it): value sets, geometry
    (positions, capsules, joint positions and axes from the DERL rules), limits, bilateral symmetry, self-contacts
    other than parent-child and same-site pairs (`contacts`), the standing-height rule (`height`), and the template
    defaults armature = damping = stiffness = 1 (`dynamics`)."""
    w = m.name
    out: list[str] = []
    try:
        d = _draft(m)
    except RobotError as e:
        return [str(e)]
    if not 1 <= m.num_limbs <= MAX_LIMBS:
        out.append(f"{w}: {m.num_limbs} limbs; expected 1..{MAX_LIMBS}")
    if m.torso_density not in DENSITIES or abs(m.torso_radius - TORSO_RADIUS) > 1e-12:
        out.append(f"{w}: torso density {m.torso_density} / radius {m.torso_radius} outside the design space")
    if len({l.density for l in m.limbs}) > 1 or (m.limbs and m.limbs[0].density not in DENSITIES):
        out.append(f"{w}: limb densities {sorted({l.density for l in m.limbs})}; expected one value from {DENSITIES}")
    ids = {l.id for l in m.limbs}
    paired = [i for p in m.mirror_pairs for i in p]
    if len(paired) != len(set(paired)) or not set(paired) <= ids:
        out.append(f"{w}: mirror pairs {m.mirror_pairs} are not disjoint pairs of existing limbs")
    for n in d.nodes:
        l = n.limb
        lw = f"{w}: limb/{l.id}"
        kinds = "".join(j.kind for j in l.joints)
        if kinds not in DOF_SETS:
            out.append(f"{lw}: joints {kinds!r}; expected one of {DOF_SETS}")
        if not _direction_ok(d, n.parent, n.site, n.theta, n.phi):
            out.append(f"{lw}: direction θ={n.theta}, φ={n.phi} at the {n.site} site is not allowed (a 3-d diagonal, "
                       f"or along its parent)")
        axes, jp = joint_axes(l.tip), joint_pos(n.theta, n.phi)
        for j in l.joints:
            jw = f"{w}: limb{j.kind}/{l.id}"
            if tuple(j.range) not in JOINT_RANGES:
                out.append(f"{jw}: range {j.range} not one of the 13 DERL intervals")
            if j.gear not in GEARS:
                out.append(f"{jw}: gear {j.gear} not in {GEARS}")
            if not np.allclose(j.axis, axes[j.kind], atol=1e-6) or not np.allclose(j.pos, jp, atol=1e-9):
                out.append(f"{jw}: pos {j.pos} / axis {j.axis}; expected {jp} / {axes[j.kind]}")
            if dynamics and (j.armature, j.damping, j.stiffness) != (1.0, 1.0, 1.0):
                out.append(f"{jw}: armature/damping/stiffness {(j.armature, j.damping, j.stiffness)}; expected 1")
    for a, b in m.mirror_pairs:
        if a in ids and b in ids:
            la, lb = m.limbs[m.index_of(a)], m.limbs[m.index_of(b)]
            if [(j.kind, j.range, j.gear) for j in la.joints] != [(j.kind, j.range, j.gear) for j in lb.joints]:
                out.append(f"{w}: mirror pair ({a}, {b}) has different joints")
            if abs(la.length - lb.length) > 1e-9:
                out.append(f"{w}: mirror pair ({a}, {b}) has different lengths")
    if not out and not _mirror_ok(d):
        out.append(f"{w}: not bilaterally symmetric (pairs must mirror each other in the xz plane, other limbs lie in it)")
    com_y, touching = robot_physics(m)
    if abs(com_y) > SYMMETRY_TOL:
        out.append(f"{w}: centre of mass y = {com_y:.3g} m; expected |y| <= {SYMMETRY_TOL}")
    if contacts:
        bad = touching - d.same_site_pairs()
        if bad:
            out.append(f"{w}: self-contacts at the rest pose between {sorted(tuple(sorted(p)) for p in bad)}")
    if height:
        want = d.standing_height()
        if abs(m.height - want) > 1e-9:
            out.append(f"{w}: height {m.height}; the standing-height rule gives {want}")
    return out
