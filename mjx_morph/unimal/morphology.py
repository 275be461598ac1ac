"""The `Morphology` value: one UNIMAL robot, a sphere torso with a tree of capsule limbs.

Everything the rest of the project knows about a robot goes through this value: the reader builds it from
MetaMorph files, the generator and the variants make new ones, the MJCF writer and the simulation consume it.
It is immutable (tuples of frozen dataclasses); change it with `dataclasses.replace`.

Conventions:
- lengths in metres, joint ranges in degrees (the files use `compiler angle="degree"`);
- a limb's body frame is never rotated, so body frame = world frame at the rest pose;
- `limbs` are in MuJoCo body order (depth-first document order of the robot file), so a parent always comes
  before its children and the policy's token order is torso, limbs[0], limbs[1], ...;
- a limb's capsule runs from its body origin to `tip`; joints are written x before y.
"""
from __future__ import annotations

import dataclasses
from typing import Iterator

import numpy as np

TORSO = -1            # `Limb.parent` of a limb attached to the torso
MAX_LIMBS = 10        # design-space limit (DERL LIMB.MAX_LIMBS)
MAX_JOINTS_PER_LIMB = 2
MAX_NODES = 12        # policy tokens: torso + 10 limbs + at least one padding token (MetaMorph MAX_LIMBS)
TORSO_RADIUS = 0.1
LIMB_RADIUS = 0.05
JOINT_AXES = ("x", "y")

Vec3 = tuple[float, float, float]


@dataclasses.dataclass(frozen=True)
class Joint:
    """A hinge joint of a limb. `kind` is "x" or "y" (joint name `limbx/k` or `limby/k`): the joint slot it
    fills in the observation and action layout."""
    kind: str
    pos: Vec3                   # body frame
    axis: Vec3                  # body frame, as written (4 decimals in DERL files)
    range: tuple[float, float]  # degrees, lo < hi
    gear: float                 # motor gear; torque = gear * ctrl, ctrl in [-1, 1]
    armature: float = 1.0       # the template's `normal_joint` defaults
    damping: float = 1.0
    stiffness: float = 1.0


@dataclasses.dataclass(frozen=True)
class Limb:
    """A capsule limb `limb/<id>`. `parent` is an index into `Morphology.limbs`, or TORSO."""
    id: int
    parent: int
    pos: Vec3                   # body position in the parent's frame
    tip: Vec3                   # capsule `fromto` end; the capsule starts at the body origin
    joints: tuple[Joint, ...]   # 1 or 2, "x" before "y"
    radius: float = LIMB_RADIUS
    density: float = 1000.0

    @property
    def name(self) -> str:
        return f"limb/{self.id}"

    @property
    def length(self) -> float:
        """Capsule segment length (r + h in DERL's notation)."""
        return float(np.linalg.norm(self.tip))

    # Mass and inertia as MetaMorph's MuJoCo 2.0 computed them from the capsule (`inertiafromgeom`): a solid
    # cylinder of the capsule's radius over its segment extended by half a radius at each end. MuJoCo's 2.1.2
    # changelog records the change to the exact capsule (hemispherical caps counted: 3-5% more mass for these
    # limbs). ModuMorph's stored context bound for the lightest limb, 1.17809725, is this mass (density 500,
    # L = 0.25, r = 0.05).
    @property
    def mass(self) -> float:
        return self.density * np.pi * self.radius**2 * (self.length + self.radius)

    def principal_inertia(self) -> np.ndarray:
        """(across, across, axial): the principal moments about the capsule's centre (tip / 2), in the capsule
        geom's own frame (z along the segment; see `mass`). Two are equal, so the principal frame is not unique:
        MuJoCo's eigen-decomposition of the full tensor picks an arbitrary one (`unimal.mjcf.limb_inertial`)."""
        m, r, h = self.mass, self.radius, self.length + self.radius
        across = m * (3.0 * r * r + h * h) / 12.0
        return np.array([across, across, m * r * r / 2.0])

    def joint(self, kind: str) -> Joint | None:
        for j in self.joints:
            if j.kind == kind:
                return j
        return None


@dataclasses.dataclass(frozen=True)
class Morphology:
    """A UNIMAL robot. `height` is the torso's standing z as written in the robot file (z0, floor at 0)."""
    name: str
    height: float
    limbs: tuple[Limb, ...]
    torso_density: float = 1000.0
    torso_radius: float = TORSO_RADIUS
    mirror_pairs: tuple[tuple[int, int], ...] = ()  # limb ids grown together as mirror images

    # ---- sizes -------------------------------------------------------------------------------------------
    @property
    def num_limbs(self) -> int:
        return len(self.limbs)

    @property
    def num_nodes(self) -> int:
        """Policy tokens used: torso + limbs."""
        return 1 + len(self.limbs)

    @property
    def dof(self) -> int:
        return sum(len(l.joints) for l in self.limbs)

    # ---- tree --------------------------------------------------------------------------------------------
    def children(self, index: int) -> list[int]:
        """Indices of the limbs attached to limb `index` (or to the torso for TORSO)."""
        return [i for i, l in enumerate(self.limbs) if l.parent == index]

    def depth(self, index: int) -> int:
        """1 for a limb on the torso, 2 for its children, ..."""
        d = 0
        while index != TORSO:
            index = self.limbs[index].parent
            d += 1
        return d

    @property
    def tree_depth(self) -> int:
        """Depth of the deepest limb below the torso (0 for a bare torso)."""
        return max((self.depth(i) for i in range(len(self.limbs))), default=0)

    def index_of(self, limb_id: int) -> int:
        for i, l in enumerate(self.limbs):
            if l.id == limb_id:
                return i
        raise KeyError(f"{self.name}: no limb with id {limb_id}")

    def joints(self) -> Iterator[tuple[int, Joint]]:
        """(limb index, joint) in MuJoCo joint order = actuator order."""
        for i, l in enumerate(self.limbs):
            for j in l.joints:
                yield i, j

    def rest_positions(self) -> np.ndarray:
        """World positions of the limb body origins at the rest pose, torso at (0, 0, height). Shape (L, 3)."""
        out = np.zeros((len(self.limbs), 3))
        for i, l in enumerate(self.limbs):
            base = np.array([0.0, 0.0, self.height]) if l.parent == TORSO else out[l.parent]
            out[i] = base + np.asarray(l.pos)
        return out

    # ---- mass --------------------------------------------------------------------------------------------

    @property
    def torso_mass(self) -> float:
        return self.torso_density * 4.0 / 3.0 * np.pi * self.torso_radius**3

    @property
    def total_mass(self) -> float:
        return self.torso_mass + sum(l.mass for l in self.limbs)     # limbs as MetaMorph's MuJoCo 2.0 (Limb.mass)
