"""Pad one robot onto a shared tree: the MJCF of the padded robot and its index tables.

Every slot of the shared tree becomes one body with exactly two hinge joints (x then y), one capsule geom and two
motors, so all padded robots of a set compile to models of one static structure (MJX keeps the tree static):
- a slot the robot uses gets the robot's limb: its body position, capsule (`fromto`, radius, density) and joints,
  written with exactly the numbers of the robot's own file, so MuJoCo computes the same masses and inertias;
- a limb with one joint gets a second, *locked* joint in the other slot: large armature, damping and stiffness,
  a tiny range, gear 0; it stays at 0 to within ~1e-6 rad;
- a slot the robot does not use is *inert*: at its parent's origin, near-zero mass (explicit `<inertial>`), a tiny
  capsule, two locked joints, gear 0. Its geom can never make contact: the stacked model gives inert geoms a very
  negative margin (see `model.py`), which MJX's constraint builder treats as "never active".
Observation and action masks hide locked joints and inert slots (`model.py`).

Masses: a real slot's capsule is written exactly as in the robot's file, with an explicit `<inertial>` that gives
it the mass and inertia MetaMorph's MuJoCo 2.0 computed (`unimal.mjcf.limb_inertial`: a cylinder over the
segment plus one radius; current MuJoCo counts the hemispherical caps, 3-5% more), as the robot alone gets them
(`compile_model`).

The world (floor, incline, height field) and the options (solver iterations, self-collision) come from the caller;
robot geoms use contype 1 and conaffinity 1 with self-collision on, 0 with it off; terrain geoms contype 0,
conaffinity 1, so with self-collision off only robot-terrain pairs are ever generated. With self-collision on and
`SolverOptions.self_pairs` given (the slot pairs that can touch, `selfcontact.py`), every other slot pair that is not
parent-child is excluded (`<contact><exclude>`); the list is the same for every robot of the set, so the static
MJX structure stays shared.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..unimal.mjcf import format_number as _num, format_vector as _vec  # the writer's exact formatting
from ..unimal.mjcf import limb_inertial        # MetaMorph's limb masses, as the robot alone compiles them
from ..unimal.morphology import Joint, Morphology
from .selfcontact import candidate_slot_pairs
from .supertree import SharedTree


# Locked joints. Armature keeps the dof still inside the constraint solve, Euler's implicit damping inside the
# integration, the spring pulls it back; stable since dt * stiffness / (armature / dt + damping) << 1. Measured
# (MuJoCo C, padded vs alone, 100 train robots, 25 control steps, 5 / 8 iterations, self-collision and the box
# floor): locked dofs stay within ~1e-6 rad; softer locks (stiffness and damping 1e5) let bodies drift 3e-4 m in
# 0.5 s. The armature sets the padding's own error: what the robot feels of a locked dof is its inertia inside
# the constraint solve, so the error falls as 1/armature (median / max over robots: armature 1e3 3.9e-5 / 3.1e-2,
# 1e4 3.9e-6 / 1.9e-3, 1e5 1.0e-6 / 6.7e-6, 1e6 5.4e-7 / 5.0e-6 m), while stiffer springs and damping (1e9) change
# nothing. The error first appears as ~5e-9 m after the first control step at any armature, and grows at contact
# events, less the larger the armature: max over robots (train / test / gen/train / gen/test) 1e5: 6.7e-6 / 8.8e-6 /
# 1.9e-5 / 1.4e-5, 1e6: 5.0e-6 / 4.0e-6 / 7.0e-6 / 3.1e-5 (gen-1-47), 1e7: 7.8e-6 / 3.1e-6 / 3.3e-6 / 7.8e-6 m. 1e7 is
# the first value with every robot of these four sets under issue 12's 1e-5 m. (An earlier measurement, before
# the solver tolerance was rescaled by trace(M) in `model.compile_padded`, found large armatures less accurate;
# now they are not. docs/benchmarks.md, "Fidelity", has the MJX checks and the GPU instability counts.)
LOCK_ARMATURE = 1.0e7
LOCK_DAMPING = 1.0e7
LOCK_STIFFNESS = 1.0e7
LOCK_RANGE_DEG = 1.0            # pad joints are limited (jnt_limited is static in MJX); never reached
INERT_MASS = 1.0e-6
INERT_INERTIA = 1.0e-9
INERT_RADIUS = 1.0e-3


@dataclasses.dataclass(frozen=True)
class WorldSpec:
    """What the task puts around the robot: MJCF snippets and the torso's start pose.

    `origin` is where this world's origin lies in MetaMorph's world: the simulation is MetaMorph's world moved by
    -origin (positions here + origin = MetaMorph's). The planes put it at the torso's start on the ground, so that
    contacts are decided near z = 0 where float32 resolves positions finely (MetaMorph's floor top is at z = 1, where
    float32's spacing is 1.19e-7 m; the incline's start at x = -72 m, z = -11.7 m, where it is 7.6e-6 m)."""
    assets: str = ""                      # inside <asset>
    geoms: str = ""                       # inside <worldbody>, before the robot (in this world's frame)
    incline_deg: float = 0.0              # torso start pose of the incline task (`start_pose`)
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def start_pose(self, z0: float):
        """Torso start position (this world's frame) and euler angles (degrees, or None) for a robot of standing
        height z0: in MetaMorph's world on the floor top z = 1, or 2 m from the lower end of the tilted slab,
        perpendicular to it."""
        ox, oy, oz = self.origin
        if self.incline_deg:
            a = math.radians(self.incline_deg)
            return (math.cos(a) * -73.0 - ox, -oy, (1.0 - math.sin(a) * 73.0 - oz) + z0), (0.0, -self.incline_deg, 0.0)
        return (-ox, -oy, (1.0 - oz) + z0), None


@dataclasses.dataclass(frozen=True)
class SolverOptions:
    """Solver and contact options of the padded models.

    self_collision      robot geoms collide with each other (parent-child pairs are always filtered)
    self_collision_cut  with self-collision: `model.build_stacked_model` finds the slot pairs that can touch
                        (`selfcontact.py`) and fills in `self_pairs`; False keeps every pair (for comparisons)
    self_pairs          with self-collision and the cut on: the slot pairs (s, t), s < t, that keep their
                        contacts, every other pair that is not parent-child is excluded (None: none excluded)
    self_pair_budget    with self-collision: MJX collides only this many capsule-capsule pairs per env, the ones
                        whose bounding spheres are closest (MJX's `max_geom_pairs`); `model.build_stacked_model`
                        sets it to the most pairs of two real limbs any robot has, and gives inert geoms a bounding
                        radius of -1e4 m so they are never among the closest: then no robot loses a pair
                        (None: every pair, as without a budget)
    contact_budget      MJX keeps at most this many contacts per env, the deepest (MJX's `max_contact_points`,
                        over all contacts: they all have condim 3); None: every contact slot of every pair
    """
    iterations: int = 16            # the env's default (env.EnvConfig): the solve stops at its tolerance before it
    ls_iterations: int = 8
    self_collision: bool = True
    timestep: float = 0.005
    self_collision_cut: bool = True
    self_pairs: frozenset | None = None
    self_pair_budget: int | None = None
    contact_budget: int | None = None

    def option_xml(self) -> str:
        return (f'  <option timestep="{_num(self.timestep)}" iterations="{self.iterations}" '
                f'ls_iterations="{self.ls_iterations}">\n'
                '    <flag filterparent="enable"/>\n'
                '  </option>')


def _joint(name: str, j: Joint | None, kind: str, indent: str) -> str:
    if j is None:   # locked pad joint
        axis = "1 0 0" if kind == "x" else "0 1 0"
        return (f'{indent}<joint name="{name}" pos="0 0 0" axis="{axis}" range="{-LOCK_RANGE_DEG} {LOCK_RANGE_DEG}" '
                f'armature="{_num(LOCK_ARMATURE)}" damping="{_num(LOCK_DAMPING)}" stiffness="{_num(LOCK_STIFFNESS)}"/>')
    return (f'{indent}<joint name="{name}" pos="{_vec(j.pos)}" axis="{_vec(j.axis)}" range="{_vec(j.range)}" '
            f'armature="{_num(j.armature)}" damping="{_num(j.damping)}" stiffness="{_num(j.stiffness)}"/>')


def excluded_slot_pairs(tree: SharedTree, options: SolverOptions) -> list[tuple[int, int]]:
    """The slot pairs (s, t), s < t, whose contacts the padded models exclude: with self-collision on, the cut on
    and `self_pairs` given, every pair that is neither parent-child nor kept; else none."""
    if not (options.self_collision and options.self_collision_cut and options.self_pairs is not None):
        return []
    return sorted(candidate_slot_pairs(tree) - options.self_pairs)


def _body_name(slot: int) -> str:
    return "torso/0" if slot == 0 else f"slot/{slot}"


def padded_mjcf(m: Morphology, tree: SharedTree, robot: int, world: WorldSpec = WorldSpec(),
                options: SolverOptions = SolverOptions()) -> str:
    """MJCF text of robot `m` (index `robot` of the tree's set) padded onto `tree`, inside `world`."""
    slots = tree.slot_of[robot]
    limb_of_slot = {s: i for i, s in enumerate(slots)}
    ca = 1 if options.self_collision else 0
    lines = [
        '<mujoco model="padded">',  # one name for all: name addresses are static in MJX
        '  <compiler angle="degree"/>',
        options.option_xml(),
        "  <default>",
        '    <motor ctrlrange="-1 1" ctrllimited="true"/>',
        '    <joint type="hinge" limited="true" solimplimit="0 0.99 0.01"/>',
        f'    <geom type="capsule" condim="3" friction="0.7 0.1 0.1" contype="1" conaffinity="{ca}"/>',
        "  </default>",
    ]
    if world.assets:
        lines += ["  <asset>", world.assets, "  </asset>"]
    lines.append("  <worldbody>")
    if world.geoms:
        lines.append(world.geoms)
    pos, eul = world.start_pose(m.height)
    euler = f' euler="{_vec(eul)}"' if eul is not None else ""
    lines += [
        f'    <body name="torso/0" pos="{_vec(pos)}"{euler}>',
        '      <freejoint name="root"/>',
        f'      <geom name="torso/0" type="sphere" size="{_num(m.torso_radius)}" density="{_num(m.torso_density)}"/>',
    ]

    def write(slot: int, indent: str) -> None:
        i = limb_of_slot.get(slot)
        if i is None:
            lines.append(f'{indent}<body name="slot/{slot}" pos="0 0 0">')
            for k in "xy":
                lines.append(_joint(f"slot{k}/{slot}", None, k, indent + "  "))
            lines.append(f'{indent}  <inertial pos="0 0 0" mass="{_num(INERT_MASS)}" '
                         f'diaginertia="{_num(INERT_INERTIA)} {_num(INERT_INERTIA)} {_num(INERT_INERTIA)}"/>')
            lines.append(f'{indent}  <geom name="slot/{slot}" size="{_num(INERT_RADIUS)} {_num(INERT_RADIUS)}"/>')
        else:
            l = m.limbs[i]
            lines.append(f'{indent}<body name="slot/{slot}" pos="{_vec(l.pos)}">')
            for k in "xy":
                lines.append(_joint(f"slot{k}/{slot}", l.joint(k), k, indent + "  "))
            lines.append(f'{indent}  <geom name="slot/{slot}" fromto="0 0 0 {_vec(l.tip)}" size="{_num(l.radius)}" '
                         f'density="{_num(l.density)}"/>')
            lines.append(f"{indent}  {limb_inertial(l)}")
        for c in tree.children(slot):
            write(c, indent + "  ")
        lines.append(f"{indent}</body>")

    for c in tree.children(0):
        write(c, "      ")
    lines += ["    </body>", "  </worldbody>"]
    excluded = excluded_slot_pairs(tree, options)
    if excluded:
        lines.append("  <contact>")
        lines += [f'    <exclude body1="{_body_name(s)}" body2="{_body_name(t)}"/>' for s, t in excluded]
        lines.append("  </contact>")
    custom = []
    if options.self_collision and options.self_pair_budget is not None:
        custom.append(f'    <numeric name="max_geom_pairs" data="{int(options.self_pair_budget)}"/>')
    if options.contact_budget is not None:
        custom.append(f'    <numeric name="max_contact_points" data="{int(options.contact_budget)}"/>')
    if custom:
        lines += ["  <custom>", *custom, "  </custom>"]
    lines.append("  <actuator>")
    for s in range(1, tree.num_slots):
        i = limb_of_slot.get(s)
        for k in "xy":
            j = m.limbs[i].joint(k) if i is not None else None
            gear = j.gear if j is not None else 0.0
            lines.append(f'    <motor name="slot{k}/{s}" joint="slot{k}/{s}" gear="{_num(gear)}"/>')
    lines += ["  </actuator>", "</mujoco>", ""]
    return "\n".join(lines)


@dataclasses.dataclass(frozen=True)
class PadTables:
    """Index tables of one padded robot (numpy, stacked along the robot axis by `model.py`).

    body_of_token[t]   body id (slot + 1) of policy token t (0 = torso, then limbs in the robot's own order);
                       padding tokens point at the torso and are masked.
    node_mask[t]       True for a real token (torso and limbs).
    act_mask[2t+k]     True where token t has a real joint of kind k (0 = x, 1 = y).
    jnt_of_action[2t+k] joint id (1 + 2*(slot-1) + k) of that action entry; 1 where masked.
    ctrl_src[a]        for actuator a of the padded model, the action entry driving it, or 24 (= a zero) if none.
    real_dof[v]        True for the dofs that are real (free joint and real hinges); pad dofs stay at 0.
    """
    body_of_token: np.ndarray
    node_mask: np.ndarray
    act_mask: np.ndarray
    jnt_of_action: np.ndarray
    ctrl_src: np.ndarray
    real_qpos: np.ndarray
    real_dof: np.ndarray


def pad_tables(m: Morphology, tree: SharedTree, robot: int, max_nodes: int = 12) -> PadTables:
    if m.num_nodes > max_nodes:
        raise ValueError(f"{m.name}: {m.num_nodes} nodes, the policy has {max_nodes} tokens")
    slots = tree.slot_of[robot]
    nu = 2 * tree.num_limb_slots
    body_of_token = np.ones(max_nodes, np.int32)
    node_mask = np.zeros(max_nodes, bool)
    node_mask[0] = True
    act_mask = np.zeros(2 * max_nodes, bool)
    jnt_of_action = np.ones(2 * max_nodes, np.int32)
    ctrl_src = np.full(nu, 2 * max_nodes, np.int32)
    real_qpos = np.zeros(7 + nu, bool)
    real_dof = np.zeros(6 + nu, bool)
    real_qpos[:7] = True
    real_dof[:6] = True
    for i, l in enumerate(m.limbs):
        t = i + 1
        s = slots[i]
        body_of_token[t] = s + 1
        node_mask[t] = True
        for k, kind in enumerate("xy"):
            if l.joint(kind) is not None:
                a = 2 * (s - 1) + k          # actuator = joint - 1 = dof - 6 = qpos - 7
                act_mask[2 * t + k] = True
                jnt_of_action[2 * t + k] = 1 + a
                ctrl_src[a] = 2 * t + k
                real_qpos[7 + a] = True
                real_dof[6 + a] = True
    return PadTables(body_of_token, node_mask, act_mask, jnt_of_action, ctrl_src, real_qpos, real_dof)
