"""DERL's UNIMAL design space: the value sets and the geometry rules of a limb.

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

`tip_geometry` reads (θ, φ, h) back from a capsule's tip; `topology_key` names the shape of a limb tree (train and
test sets are kept apart by it). `outside_bounds` lists the values of a robot far beyond all of this (a 50 m limb,
a gear of 1e6): generous plausibility bounds that every robot of the design space passes with a wide margin.

Decision where DERL leaves room (ours): `sph2cart` uses exact cos/sin values of multiples of 45°, so it gives the
same bits on every machine. numpy's sin/cos may differ by an ulp between CPUs, and DERL's 2-decimal rounding hits
exact ties (0.35 · ½ = 0.175) that such an ulp flips.
"""
from __future__ import annotations

import math
from typing import Sequence

import mujoco
import numpy as np

from .morphology import LIMB_RADIUS, TORSO, Morphology

# ---- DERL's config values -------------------------------------------------------------------------------------
THETAS = tuple(float(t) for t in range(0, 360, 45))   # degrees from +x
PHIS = (90.0, 135.0, 180.0)                           # degrees from +z: horizontal, 45° down, straight down
LIMB_HEIGHTS = (0.2, 0.3, 0.4)                        # h; the capsule segment is r + h long
DOF_SETS = ("x", "y", "xy")
JOINT_RANGES = tuple((float(a), float(b)) for a, b in (
    (-30, 0), (0, 30), (-30, 30), (-45, 45), (-45, 0), (0, 45), (-60, 0), (0, 60), (-60, 60), (-90, 0), (0, 90),
    (-60, 30), (-30, 60)))
GEARS = (150.0, 200.0, 250.0, 300.0)
DENSITIES = (500.0, 600.0, 700.0, 800.0, 900.0, 1000.0)
FLOOR_OFFSET = 0.2                                    # standing height = lowest point's depth + this
SITES = ("mid", "btm")                                # growth sites of a limb

# ---- plausibility bounds (ours) ---------------------------------------------------------------------------------
# A robot beyond these is outside the UNIMAL design space by far (`outside_bounds`): the loaders refuse it
# (`reader.load_robot`, `sets.load_set`) and `experiments.robots validate` reports it. What DERL's value sets above
# give, and what the 202 original robots, `assets/gen` and their variants (`variants.py`) contain: capsule length
# r + h = 0.25 .. 0.4525 m, limb radius 0.05 m, torso radius 0.1 m, densities 500 .. 1000 kg/m^3, gears 150 .. 300,
# joint limits -90 .. 90 degrees with spans of 30 .. 120 degrees, armature = damping = stiffness = 1 (variants:
# 0.2 .. 5), limb offsets from the parent 0.099 .. 0.51 m, standing heights 0.3 .. 1.05 m. The bounds are generous,
# 4 to 10 times beyond those values, so that hand-made variations pass and only values that make no sense for this
# robot family (a 50 m limb, a gear of 1e6, a density of 1e-6) are refused.
LIMB_LENGTH_BOUNDS = (0.05, 2.0)        # m, capsule segment |tip| (DERL: 0.25 .. 0.4525)
LIMB_RADIUS_BOUNDS = (0.01, 0.25)       # m (DERL: 0.05)
TORSO_RADIUS_BOUNDS = (0.02, 0.5)       # m (DERL: 0.1)
DENSITY_BOUNDS = (100.0, 5000.0)        # kg/m^3, torso and limbs (DERL: 500 .. 1000)
GEAR_BOUNDS = (30.0, 1500.0)            # motor gear, torque at ctrl = 1 in N m (DERL: 150 .. 300)
JOINT_LIMIT_MAX = 135.0                 # degrees: -135 <= lo < hi <= 135 (DERL: -90 .. 90)
JOINT_SPAN_MIN = 5.0                    # degrees, hi - lo (DERL: 30 .. 120)
JOINT_PARAM_MAX = 50.0                  # armature, damping, stiffness (template: 1; variants: 0.2 .. 5)
LIMB_OFFSET_MAX = 2.0                   # m, |body pos| in its parent's frame (DERL: 0.099 .. 0.51)
HEIGHT_MAX = 5.0                        # m, the torso's standing height (DERL: 0.3 .. 1.05)

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


def unit(theta: float, phi: float) -> np.ndarray:
    """The unrounded unit vector of direction (θ, φ), degrees (multiples of 45°)."""
    ct, st = _cos_sin(theta)
    cp, sp = _cos_sin(phi)
    return np.array([sp * ct, sp * st, cp])


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
    """Joint position in the limb's body frame: on the proximal tip of the capsule."""
    return sph2cart(_R, theta + 180.0, 180.0 - phi)


# tip (rounded) -> (theta, phi, h); phi = 180° gives the same tip for every theta: keep theta = 0
_TIP_TABLE: dict[tuple[float, float, float], tuple[float, float, float]] = {}
for _h in LIMB_HEIGHTS:
    for _p in PHIS:
        for _t in THETAS:
            _TIP_TABLE.setdefault(sph2cart(_R + _h, _t, _p), (_t, _p, _h))


def tip_geometry(tip: Sequence[float]) -> tuple[float, float, float] | None:
    """(θ, φ, h) of a capsule whose `fromto` is 0 → `tip` (compared after rounding to 2 decimals), None when the
    tip is not v(r + h, θ, φ) of the design space. A vertical tip (φ = 180°) gives θ = 0."""
    return _TIP_TABLE.get(tuple(round(float(x), 2) + 0.0 for x in tip))


def topology_key(m: Morphology) -> str:
    """Canonical key of the limb tree's shape, independent of child order, ids and geometry: each node is
    "(" + its children's keys sorted + ")", starting from the torso. E.g. a torso with two bare limbs: "(()())"."""
    def key(index: int) -> str:
        return "(" + "".join(sorted(key(c) for c in m.children(index))) + ")"
    return key(TORSO)


def outside_bounds(m: Morphology, *, skip_invalid: bool = False) -> list[tuple[str, str]]:
    """(element, message) for each value of `m` beyond the plausibility bounds above (torso first, then each limb
    with its joints and motors); empty for every robot of DERL's design space. The element is named as in the robot
    file (`<body name="limb/2">`, `<joint name="limbx/2">`, `<motor joint="limbx/2">`), so a caller adds the file:
    `RobotError(file, *item)`. `skip_invalid` leaves out the values that `validate.check_morphology` already
    reports as meaningless (non-positive sizes, densities and gears, negative armature, damping or stiffness, a
    range that is not -180 <= lo < hi <= 180), so that a caller running both reports each value once."""
    out: list[tuple[str, str]] = []

    def add(element: str, what: str, value: float, bounds: tuple[float, float], unit: str = "",
            invalid: bool = False) -> None:
        lo, hi = bounds
        if lo <= value <= hi or (skip_invalid and invalid):
            return
        u = f" {unit}" if unit else ""
        out.append((element, f"{what} {value:g}{u} is outside the UNIMAL design space; expected {lo:g} to {hi:g}{u}"))

    torso = '<body name="torso/0">'
    add(torso, "standing height", m.height, (-math.inf, HEIGHT_MAX), "m")
    add(torso, "sphere radius", m.torso_radius, TORSO_RADIUS_BOUNDS, "m", m.torso_radius <= 0)
    add(torso, "density", m.torso_density, DENSITY_BOUNDS, "kg/m^3", m.torso_density <= 0)
    for l in m.limbs:
        body = f'<body name="{l.name}">'
        add(body, "offset from the parent |pos|", float(np.linalg.norm(l.pos)), (0.0, LIMB_OFFSET_MAX), "m")
        add(body, "capsule length", l.length, LIMB_LENGTH_BOUNDS, "m", l.length <= 1e-6)
        add(body, "capsule radius", l.radius, LIMB_RADIUS_BOUNDS, "m", l.radius <= 0)
        add(body, "density", l.density, DENSITY_BOUNDS, "kg/m^3", l.density <= 0)
        for j in l.joints:
            joint = f'<joint name="limb{j.kind}/{l.id}">'
            lo, hi = j.range
            if (not -JOINT_LIMIT_MAX <= lo < hi <= JOINT_LIMIT_MAX or hi - lo < JOINT_SPAN_MIN) and not (
                    skip_invalid and not -180 <= lo < hi <= 180):
                out.append((joint, f"range ({lo:g}, {hi:g}) degrees is outside the UNIMAL design space; expected "
                                   f"{-JOINT_LIMIT_MAX:g} <= lo < hi <= {JOINT_LIMIT_MAX:g}, hi - lo >= "
                                   f"{JOINT_SPAN_MIN:g}"))
            for attr in ("armature", "damping", "stiffness"):
                value = getattr(j, attr)
                add(joint, attr, value, (0.0, JOINT_PARAM_MAX), invalid=value < 0)
            add(f'<motor joint="limb{j.kind}/{l.id}">', "gear", j.gear, GEAR_BOUNDS, invalid=j.gear <= 0)
    return out
