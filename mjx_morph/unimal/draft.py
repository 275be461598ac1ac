"""A robot as DERL geometry: a mutable working copy (`Draft`) and the checks a robot must pass.

`Draft.from_morphology` reads the limb geometry (θ, φ, h and attachment site of every limb) back from each limb's
`tip` and `pos`; this works for all 202 original robots. A robot outside this geometry raises `RobotError`.
`check_design_space` runs every check on a finished robot.

Decisions where DERL leaves room (ours):
- Symmetry test: MuJoCo's centre of mass of the torso subtree at the rest pose (`mj_forward`, torso at the origin)
  must have |y| <= `SYMMETRY_TOL` = 1e-9 m. DERL compares with exact float equality after one `mj_step`, which
  also rejects mirror-image robots whose float sums do not cancel exactly; a mirror-image robot gives
  |y| ~ 1e-17 here, a real asymmetry >= ~1e-3 m. A cheap structural mirror test (`mirror_ok`: world positions of
  every pair mirror each other, unpaired limbs lie in the xz plane) runs first and skips the compile when it fails.
- Self-contact: `mj_forward` contacts of the compiled robot (parent-child pairs filtered) that overlap by more
  than `CONTACT_TOL` = 1e-6 m. Capsules touching exactly (distance 0 up to float noise) are common on this grid,
  e.g. two limbs leaving one site in opposite directions (-x and +x); MuJoCo reports them or not depending on
  ~1e-17 m of noise, and the originals are full of them (54 of 202 robots), so they do not count, on every machine.
  Allowed: the two limbs of a same-site pair (`physics_ok`).
- Directions: DERL samples 24 (θ, φ); the original robots use only 13 directions. The missing 3-d diagonals
  (θ = 45°, 135°, ... with φ = 135°) can only appear as mirror pairs, and for those DERL's 2-decimal rounding hits
  exact ties that numpy's sin/cos resolve differently for θ and 360° - θ, so DERL's symmetry test rejected them
  (by float noise). `direction_ok` rejects them explicitly, which gives exactly the 13 directions.
- Besides DERL's rule "no limb along its parent's direction at the parent's `mid` site", `direction_ok` also
  rejects a limb pointing straight back along its parent (it would lie inside the parent; parent-child contacts
  are ignored, so the contact test cannot see it). None of the 202 original robots has one.
- Standing height (DERL's `set_head_pos`): torso at the origin, lowest `btm_pos` point z_min over the torso's
  (0, 0, -0.1) and every limb's v(2r + h) at the rest pose (computed kinematically: bodies are never rotated, so
  this equals `mj_forward`; one `mj_step` would lower everything by ~2.5e-4 m, which never changes the result after
  rounding because z_min is a multiple of 0.01), height = round(-z_min + 0.2, 2). We use DERL's creation-time
  btm_pos v(2r + h) also after `limb_params` (DERL's `limb_params` writes v(r + h) there, a bug).
"""
from __future__ import annotations

import dataclasses
from typing import Sequence

import mujoco
import numpy as np

from .design_space import (DENSITIES, DOF_SETS, FLOOR_OFFSET, GEARS, JOINT_RANGES, LIMB_HEIGHTS, SITES, joint_axes,
                           joint_pos, sph2cart, tip_geometry, unit)
from .errors import RobotError
from .mjcf import compile_model
from .morphology import LIMB_RADIUS, MAX_LIMBS, TORSO, TORSO_RADIUS, Limb, Morphology

SYMMETRY_TOL = 1e-9                # metres, |y| of the centre of mass
CONTACT_TOL = 1e-6                 # metres: a contact needs more overlap than this (exact touching does not count)

_R = LIMB_RADIUS


def _add(a: Sequence[float], b: Sequence[float]) -> tuple[float, float, float]:
    return (float(a[0] + b[0]), float(a[1] + b[1]), float(a[2] + b[2]))


# ---- a mutable working copy of a robot ------------------------------------------------------------------------
@dataclasses.dataclass
class Node:
    limb: Limb                 # `limb.parent` is stale here; `parent` holds the parent's limb id
    parent: int | None         # parent limb id, None for the torso
    site: str                  # "torso", "mid" or "btm" (of the parent)
    theta: float
    phi: float
    h: float


@dataclasses.dataclass
class Draft:
    name: str
    height: float
    torso_density: float
    torso_radius: float
    limb_density: float
    nodes: list[Node]          # sibling order = order in this list
    pairs: list[tuple[int, int]]

    @classmethod
    def from_morphology(cls, m: Morphology) -> "Draft":
        """Working copy of a robot, with the DERL geometry of every limb read back from `tip` and `pos`."""
        nodes: list[Node] = []
        ids: list[int] = []
        d = cls(m.name, m.height, m.torso_density, m.torso_radius,
                m.limbs[0].density if m.limbs else DENSITIES[-1], nodes, [tuple(p) for p in m.mirror_pairs])
        for l in m.limbs:
            geo = tip_geometry(l.tip)
            if geo is None or abs(l.radius - _R) > 1e-9:
                raise RobotError(m.name, f'<body name="{l.name}">',
                                 f"capsule fromto 0 -> {tuple(l.tip)} radius {l.radius} is not a UNIMAL generator "
                                 f"limb (expected v(0.05 + h, θ, φ), h in {LIMB_HEIGHTS}, radius 0.05)")
            theta, phi, h = geo
            parent = None if l.parent == TORSO else ids[l.parent]
            sites = ("torso",) if parent is None else SITES
            site = None
            for s in sites:
                if np.allclose(l.pos, d.limb_pos(parent, s, theta, phi), atol=1e-6):
                    site = s
                    break
            if site is None:
                raise RobotError(m.name, f'<body name="{l.name}">',
                                 f"pos {tuple(l.pos)} is not at a growth site of its parent "
                                 f"(expected site + v(p_r, θ, φ) at the torso centre or the parent's mid/btm site)")
            nodes.append(Node(l, parent, site, theta, phi, h))
            ids.append(l.id)
        return d

    def copy(self) -> "Draft":
        return dataclasses.replace(self, nodes=[dataclasses.replace(n) for n in self.nodes], pairs=list(self.pairs))

    def node(self, limb_id: int) -> Node:
        for n in self.nodes:
            if n.limb.id == limb_id:
                return n
        raise KeyError(limb_id)

    def children(self, limb_id: int | None) -> list[Node]:
        return [n for n in self.nodes if n.parent == limb_id]

    def dfs(self) -> list[Node]:
        out: list[Node] = []

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
        """The standing-height rule (see the module notes)."""
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


# ---- checks ---------------------------------------------------------------------------------------------------
def mirror_ok(d: Draft) -> bool:
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


def physics_ok(d: Draft, base_contacts: set[frozenset[str]]) -> bool:
    """Symmetric centre of mass, and no contacts beyond `base_contacts` and the same-site pairs."""
    com_y, contacts = robot_physics(d.to_morphology())
    return abs(com_y) <= SYMMETRY_TOL and not (contacts - base_contacts - d.same_site_pairs())


def direction_ok(d: Draft, parent: int | None, site: str, theta: float, phi: float) -> bool:
    """Whether a limb may leave `site` of limb `parent` (None: the torso) in direction (θ, φ) (see the module
    notes)."""
    if phi == 135.0 and int(round(theta)) % 90 == 45:   # a 3-d diagonal
        return False
    if parent is None:
        return True
    p = d.node(parent)
    c = float(np.dot(unit(theta, phi), unit(p.theta, p.phi)))
    if c < -1 + 1e-9:                      # straight back into the parent
        return False
    return not (site == "mid" and c > 1 - 1e-9)


# ---- reading a finished robot ---------------------------------------------------------------------------------
def limb_geometry(m: Morphology) -> list[dict]:
    """Per limb (body order): DERL's θ, φ (degrees), h, and the attachment site ("torso", "mid" or "btm")."""
    return [dict(theta=n.theta, phi=n.phi, h=n.h, site=n.site) for n in Draft.from_morphology(m).nodes]


def standing_height(m: Morphology) -> float:
    """DERL's `set_head_pos` height for the robot's geometry (see the module notes)."""
    return Draft.from_morphology(m).standing_height()


def check_design_space(m: Morphology, *, contacts: bool = True, height: bool = True,
                       dynamics: bool = True) -> list[str]:
    """Problems of a robot w.r.t. the generator's design space (empty when inside it): value sets, geometry
    (positions, capsules, joint positions and axes from the DERL rules), limits, bilateral symmetry, self-contacts
    other than parent-child and same-site pairs (`contacts`), the standing-height rule (`height`), and the template
    defaults armature = damping = stiffness = 1 (`dynamics`)."""
    w = m.name
    out: list[str] = []
    try:
        d = Draft.from_morphology(m)
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
        if not direction_ok(d, n.parent, n.site, n.theta, n.phi):
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
    if not out and not mirror_ok(d):
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
