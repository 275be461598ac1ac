"""Dynamics and kinematics variants of UNIMAL robots: MetaMorph's 2400 = 100 robots x 6 change
types x 4, named `<robot id>_<change>_<k>`, k = 0..3.

The original variant files are not public, so the value ranges below are OUR reconstruction, not
MetaMorph's. Each variant changes exactly one change type and nothing else (names aside):

| change        | what changes | how (ours) |
|---------------|--------------|------------|
| `armature`    | `Joint.armature` of every limb joint | one value v for all joints, log-uniform in [0.2, 5] and re-drawn while 0.8 <= v <= 1.25 (at least 20 % away from the template default 1), rounded to 2 decimals |
| `damping`     | `Joint.damping` of every limb joint  | same distribution as armature, drawn independently |
| `density`     | torso density, limb density (all limbs) | DERL `density` operator: both re-drawn from {500, ..., 1000}, each different from the original |
| `gear`        | `Joint.gear` | DERL `gear` operator: ½ every limb group, ½ one group (a mirror pair is one group, same values); every re-drawn gear differs from the old one, values {150, 200, 250, 300} |
| `joint_angle` | `Joint.range` | DERL `joint_angle` operator, same group rule; every re-drawn range differs from the old one, values = the 13 DERL intervals |
| `limb_params` | the `tip` of one group's capsules, the `pos` of that group's direct children, the standing height | DERL `limb_params` operator: one group gets a new h in {0.2, 0.3, 0.4} (different from its h); kept only if the robot stays symmetric and no new self-contact appears; height by the generator's standing-height rule |

Why this armature/damping range: the template default is 1 for both, and the limbs' own inertia about
their joints is small (~0.01-0.1 kg m^2), so armature dominates the joint's effective inertia; a factor of up to 5
either way gives a clearly different, still stable (timestep 0.005 s, damping integrated implicitly) robot.
Log-uniform treats halving and doubling alike.

Determinism: the 4 variants of one robot and change type come from one `numpy.random.default_rng` stream seeded
with (seed, stable hash of the robot id, stable hash of the change type) — SHA-256, not Python's salted `hash()`.
Variant k is drawn after variants 0..k-1 and is re-drawn when it equals the base robot or an earlier variant, so
the 4 variants are distinct.
"""
from __future__ import annotations

import dataclasses
import hashlib
import re
from typing import Iterable, Sequence

import numpy as np

from .errors import RobotError
from .mutations import mutate
from .morphology import Morphology

CHANGE_TYPES = ("armature", "damping", "density", "gear", "joint_angle", "limb_params")
DYNAMICS_TYPES = ("armature", "damping", "density", "gear")
KINEMATICS_TYPES = ("joint_angle", "limb_params")
JOINT_PARAM_RANGE = (0.2, 5.0)       # armature / damping: log-uniform on this interval ...
JOINT_PARAM_EXCLUDE = (0.8, 1.25)    # ... re-drawn while inside this interval around the default 1
PER_TYPE = 4
BASE_SEED = 0
_REDRAWS = 100

_NAME_RE = re.compile(r"^(?P<base>.+)_(?P<change>" + "|".join(CHANGE_TYPES) + r")_(?P<k>\d+)$")


def stable_hash(text: str) -> int:
    """A 64-bit hash of `text` that is the same in every process and on every machine."""
    return int.from_bytes(hashlib.sha256(text.encode("utf-8")).digest()[:8], "little")


def variant_name(base_id: str, change: str, k: int) -> str:
    return f"{base_id}_{change}_{k}"


def variant_change(name: str) -> tuple[str, str, int]:
    """`"<base id>_<change>_<k>"` -> (base id, change, k); raises ValueError for a name that is not a variant."""
    m = _NAME_RE.match(name)
    if not m:
        raise ValueError(f"{name!r} is not a variant name <robot id>_<change>_<k> with change in {CHANGE_TYPES}")
    return m.group("base"), m.group("change"), int(m.group("k"))


def _joint_param(rng: np.random.Generator) -> float:
    lo, hi = JOINT_PARAM_RANGE
    while True:
        v = round(float(np.exp(rng.uniform(np.log(lo), np.log(hi)))), 2)
        if not JOINT_PARAM_EXCLUDE[0] <= v <= JOINT_PARAM_EXCLUDE[1]:
            return v


def _set_joint_attr(m: Morphology, attr: str, value: float) -> Morphology:
    limbs = tuple(dataclasses.replace(l, joints=tuple(dataclasses.replace(j, **{attr: value}) for j in l.joints))
                  for l in m.limbs)
    return dataclasses.replace(m, limbs=limbs)


def make_variant(m: Morphology, change: str, rng: np.random.Generator) -> Morphology:
    """One variant of `m` for one change type (keeps `m.name`; see the module table)."""
    if change in ("armature", "damping"):
        return _set_joint_attr(m, change, _joint_param(rng))
    if change in ("density", "gear", "joint_angle", "limb_params"):
        v = mutate(m, change, rng, force_change=True)
        if v is m:
            raise RobotError(m.name, "", f"no {change} variant found (every new limb length adds a self-contact)")
        return v
    raise ValueError(f"unknown change type {change!r}; expected one of {CHANGE_TYPES}")


def robot_variants(m: Morphology, change: str, per_type: int = PER_TYPE, seed: int = BASE_SEED) -> list[Morphology]:
    """The `per_type` variants `<id>_<change>_<k>` of one robot, in k order."""
    rng = np.random.default_rng([seed, stable_hash(m.name), stable_hash(change)])
    out: list[Morphology] = []
    seen = [m]
    for k in range(per_type):
        for _ in range(_REDRAWS):
            v = make_variant(m, change, rng)
            if v not in seen:
                break
        else:
            raise RobotError(m.name, "", f"could not find {per_type} distinct {change} variants")
        seen.append(v)
        out.append(dataclasses.replace(v, name=variant_name(m.name, change, k)))
    return out


def make_variants(robots: Iterable[Morphology], per_type: int = PER_TYPE, seed: int = BASE_SEED,
                  types: Sequence[str] = CHANGE_TYPES) -> list[Morphology]:
    """Every robot's variants: for each robot (in the given order), each change type in `types`, k = 0..per_type-1.
    100 robots give 100 x 6 x 4 = 2400 variants."""
    for t in types:
        if t not in CHANGE_TYPES:
            raise ValueError(f"unknown change type {t!r}; expected one of {CHANGE_TYPES}")
    out: list[Morphology] = []
    for m in robots:
        for t in types:
            out += robot_variants(m, t, per_type, seed)
    return out
