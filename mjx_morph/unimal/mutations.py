"""DERL's mutation operators on a `Draft`, and `mutate` for a finished robot.

`grow_limb` adds one limb, or a mirror pair: two limbs on one plane site ((θ, φ) and (360° - θ, φ)) or one on
each site of a mirror-site pair (same (θ, φ)). A growth is kept only if the robot stays bilaterally symmetric and
no new self-contact appears (`mirror_ok`, `physics_ok`). The other operators are `joint_angle`, `gear`, `dof`
(½: every limb group, ½: one group; a mirror pair is one group and gets identical values), `limb_params` (one group
gets a new h; the group's capsules and its children's positions are recomputed), `density` and `delete_limb` (one
leaf group).

Decisions where DERL leaves room (ours):
- `grow_limb` and `limb_params` may add no self-contact other than a same-site pair's. A robot passed to `mutate`
  that already has other contacts (one original robot does) keeps them.
- New limb ids are max(id) + 1 (DERL keeps a counter that never reuses deleted ids; ids only need to be unique).
- When an operator cannot be applied (grow at 10 limbs or no valid growth in `ATTEMPTS` tries, delete with
  <= 2 limbs, no contact-free `limb_params` in `ATTEMPTS` tries) `mutate` returns the robot unchanged.
"""
from __future__ import annotations

import dataclasses
from typing import Iterable, Sequence

import numpy as np

from .design_space import (DENSITIES, DOF_SETS, GEARS, JOINT_RANGES, LIMB_HEIGHTS, PHIS, SITES, THETAS, joint_axes,
                           joint_pos, sph2cart)
from .draft import Draft, Node, direction_ok, mirror_ok, physics_ok, robot_physics
from .morphology import LIMB_RADIUS, MAX_LIMBS, TORSO, Joint, Limb, Morphology

MUTATION_OPS = ("grow_limb", "joint_angle", "limb_params", "dof", "density", "gear", "delete_limb")
ATTEMPTS = 50                      # DERL's grow_limb tries; also used for limb_params

_R = LIMB_RADIUS


# ---- sampling helpers -----------------------------------------------------------------------------------------
def as_rng(rng_or_seed) -> np.random.Generator:
    """`rng_or_seed` itself when it is a `numpy.random.Generator`, else `numpy.random.default_rng(rng_or_seed)`."""
    if isinstance(rng_or_seed, np.random.Generator):
        return rng_or_seed
    return np.random.default_rng(rng_or_seed)


def pick(rng: np.random.Generator, seq: Sequence, exclude=None):
    """A uniform draw from `seq`, leaving out the value `exclude` (None: leave out nothing)."""
    options = [v for v in seq if v != exclude] if exclude is not None else list(seq)
    return options[int(rng.integers(len(options)))]


def _make_joints(dof: str, theta: float, phi: float, tip, params: dict[str, tuple[tuple[float, float], float]],
                 like: Joint | None = None) -> tuple[Joint, ...]:
    axes = joint_axes(tip)
    jp = joint_pos(theta, phi)
    extra = {} if like is None else dict(armature=like.armature, damping=like.damping, stiffness=like.stiffness)
    return tuple(Joint(kind=k, pos=jp, axis=axes[k], range=params[k][0], gear=params[k][1], **extra) for k in dof)


def _sample_params(rng: np.random.Generator, dof: str) -> dict[str, tuple[tuple[float, float], float]]:
    return {k: (pick(rng, JOINT_RANGES), pick(rng, GEARS)) for k in dof}


# ---- operators on drafts (return True when the draft changed) -------------------------------------------------
def _grow(d: Draft, rng: np.random.Generator) -> bool:
    n_limbs = len(d.nodes)
    if n_limbs >= MAX_LIMBS:
        return False
    base_contacts = robot_physics(d.to_morphology())[1] if d.nodes else set()
    sites: list[tuple[int | None, str]] = [(None, "torso")] + [(n.limb.id, s) for n in d.dfs() for s in SITES]
    for _ in range(ATTEMPTS):
        parent, site = sites[int(rng.integers(len(sites)))]
        mirror = None if parent is None else d.partner(parent)
        count = 2 if mirror is not None else int(rng.integers(1, 3))
        if n_limbs + count > MAX_LIMBS:
            continue
        h = pick(rng, LIMB_HEIGHTS)
        dof = pick(rng, DOF_SETS)
        params = _sample_params(rng, dof)
        theta, phi = pick(rng, THETAS), pick(rng, PHIS)
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
        if not all(direction_ok(d, p, site, t, phi) for p, t in places):
            continue
        new_id = max((n.limb.id for n in d.nodes), default=-1) + 1
        cand = d.copy()
        for k, (p, t) in enumerate(places):
            tip = sph2cart(_R + h, t, phi)
            limb = Limb(id=new_id + k, parent=TORSO, pos=cand.limb_pos(p, site, t, phi), tip=tip,
                        joints=_make_joints(dof, t, phi, tip, params), radius=_R, density=d.limb_density)
            cand.nodes.append(Node(limb, p, site, t, phi, h))
        if count == 2:
            cand.pairs.append((new_id, new_id + 1))
        if not mirror_ok(cand):
            continue
        if not physics_ok(cand, base_contacts):
            continue
        cand.height = cand.standing_height()
        d.nodes, d.pairs, d.height = cand.nodes, cand.pairs, cand.height
        return True
    return False


def _chosen_groups(d: Draft, rng: np.random.Generator) -> list[tuple[int, ...]]:
    groups = d.groups()
    if rng.random() < 0.5:
        return groups
    return [groups[int(rng.integers(len(groups)))]]


def _joint_values(d: Draft, rng: np.random.Generator, attr: str, values: Sequence, force: bool) -> bool:
    """`joint_angle` (attr "range") and `gear` (attr "gear")."""
    if not d.nodes:
        return False
    for g in _chosen_groups(d, rng):
        first = d.node(g[0]).limb
        new = {j.kind: pick(rng, values, getattr(j, attr) if force else None) for j in first.joints}
        for lid in g:
            n = d.node(lid)
            n.limb = dataclasses.replace(n.limb, joints=tuple(
                dataclasses.replace(j, **{attr: new.get(j.kind, getattr(j, attr))}) for j in n.limb.joints))
    return True


def _dof(d: Draft, rng: np.random.Generator, force: bool) -> bool:
    if not d.nodes:
        return False
    for g in _chosen_groups(d, rng):
        first = d.node(g[0]).limb
        current = "".join(j.kind for j in first.joints)
        dof = pick(rng, DOF_SETS, current if force else None)
        params = _sample_params(rng, dof)
        for lid in g:
            n = d.node(lid)
            n.limb = dataclasses.replace(n.limb, joints=_make_joints(dof, n.theta, n.phi, n.limb.tip, params,
                                                                     like=n.limb.joints[0]))
    return True


def _density(d: Draft, rng: np.random.Generator, force: bool) -> bool:
    d.torso_density = pick(rng, DENSITIES, d.torso_density if force else None)
    d.limb_density = pick(rng, DENSITIES, d.limb_density if force else None)
    for n in d.nodes:
        n.limb = dataclasses.replace(n.limb, density=d.limb_density)
    return True


def _set_h(d: Draft, group: Iterable[int], h: float) -> None:
    for lid in group:
        n = d.node(lid)
        n.h = h
        n.limb = dataclasses.replace(n.limb, tip=sph2cart(_R + h, n.theta, n.phi))
        for c in d.children(lid):
            c.limb = dataclasses.replace(c.limb, pos=d.limb_pos(lid, c.site, c.theta, c.phi))


def _limb_params(d: Draft, rng: np.random.Generator, force: bool) -> bool:
    if not d.nodes:
        return False
    base_contacts = robot_physics(d.to_morphology())[1]
    groups = d.groups()
    for _ in range(ATTEMPTS):
        g = groups[int(rng.integers(len(groups)))]
        h = pick(rng, LIMB_HEIGHTS, d.node(g[0]).h if force else None)
        cand = d.copy()
        _set_h(cand, g, h)
        if not mirror_ok(cand) or not physics_ok(cand, base_contacts):
            continue
        cand.height = cand.standing_height()
        d.nodes, d.height = cand.nodes, cand.height
        return True
    return False


def _delete(d: Draft, rng: np.random.Generator) -> bool:
    if len(d.nodes) <= 2:
        return False
    leaves = [g for g in d.groups() if all(not d.children(lid) for lid in g)]
    g = set(leaves[int(rng.integers(len(leaves)))])
    d.nodes = [n for n in d.nodes if n.limb.id not in g]
    d.pairs = [p for p in d.pairs if p[0] not in g and p[1] not in g]
    d.height = d.standing_height()
    return True


def apply(d: Draft, op: str, rng: np.random.Generator, force: bool = False) -> bool:
    """Apply mutation operator `op` (one of `MUTATION_OPS`) to `d` in place; True when `d` changed. With `force`,
    every value the operator re-draws differs from the current one."""
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


def random_op(d: Draft, rng: np.random.Generator) -> str:
    """DERL's random operator choice: uniform over `MUTATION_OPS`, no grow at 10 limbs, no delete at <= 2 limbs,
    only grow at 0 limbs."""
    n = len(d.nodes)
    if n == 0:
        return "grow_limb"
    ops = [o for o in MUTATION_OPS if not (o == "grow_limb" and n >= MAX_LIMBS) and not (o == "delete_limb" and n <= 2)]
    return ops[int(rng.integers(len(ops)))]


def mutate(m: Morphology, op: str, rng, *, force_change: bool = False) -> Morphology:
    """Apply one DERL mutation operator (one of `MUTATION_OPS`) and return the new robot (same name).

    Returns `m` itself when the operator cannot be applied (see the module notes). With `force_change`, every
    value the operator re-draws differs from the current one (used by the variants); DERL re-draws freely."""
    if op not in MUTATION_OPS:
        raise ValueError(f"unknown mutation {op!r}; expected one of {MUTATION_OPS}")
    d = Draft.from_morphology(m)
    if not apply(d, op, as_rng(rng), force_change):
        return m
    return d.to_morphology()


def mutated_robots(robots: Sequence[Morphology], num: int, seed: int = 0, rounds: int = 1) -> list[Morphology]:
    """`num` robots made from `robots` by DERL's operators: robot k is `robots[k % len(robots)]` after `rounds`
    random operators (`random_op`), named `<parent>-mut<k>`. Robots outside the training family for fidelity checks
    (`experiments.check_sim SET mutated=1000`)."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(num):
        m = robots[k % len(robots)]
        for _ in range(rounds):
            m = mutate(m, random_op(Draft.from_morphology(m), rng), rng)
        out.append(dataclasses.replace(m, name=f"{robots[k % len(robots)].name}-mut{k}"))
    return out
