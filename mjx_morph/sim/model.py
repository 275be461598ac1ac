"""One stacked `mjx.Model` for a robot set: every robot padded onto the set's shared tree, compiled, stacked.

`build_stacked_model(robots, world, options)`:
1. builds the shared tree of the set (`supertree.py`; a test set gets its own tree),
2. writes each robot padded onto it inside the task's world (`padding.py`) and compiles it with MuJoCo,
3. fixes up the compiled models so that they share one static MJX structure (one compiled step serves all):
   `body_sameframe`, `geom_sameframe`, `body_simple` and `dof_simplenum` are set to 0 (MJX's JAX path does not
   read them; the general path is right for every robot), and every robot gets the element-wise max of
   `geom_rbound_hfield` (the height field collision window, static in MJX); the solver tolerance is rescaled per
   robot so that the locked joints' armature does not loosen it (`compile_padded`);
4. stacks the MJX models along a leading robot axis. A leaf that is identical for all robots is kept once
   (`axes` leaf None), the others get the robot axis (`axes` leaf 0); `model_for(robot)` gathers one robot's model,
   and under `vmap` over envs that is one batched gather per control step (the cheapest of the variants measured,
   see docs/benchmarks.md);
5. gives inert geoms a margin of -1e4 m: MJX activates a contact when `dist < margin`, so inert geoms never touch
   anything (in any pose, with self-collision on too) while the static contact structure stays shared; and gives
   robot-robot contacts a margin of -SELF_CONTACT_GAP (robot geoms -gap/2, world geoms +gap/2, so robot-world
   contacts keep MuJoCo's 0), see SELF_CONTACT_GAP.
With self-collision on (and `SolverOptions.self_collision_cut`, unless the caller gave `self_pairs`), step 2 first
finds the slot pairs that some robot of the set can make touch (`selfcontact.py`, cached per robot) and the padded
models exclude all other pairs; `StackedModel.self_contact` summarises the pairs MJX checks.

It also precomputes the per-robot constants the observation and action code needs (`Robots` for the policy,
`Tables` for the simulation), all as arrays with the robot axis first.
"""
from __future__ import annotations

import dataclasses
import enum
import functools
import hashlib
import time
from importlib import metadata
from typing import Any, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from ..unimal.mjcf import compile_model
from ..layout import CTX_DIM, NUM_ACTIONS, NUM_TOKENS, OBS_DIM, Robots
from ..unimal.morphology import Morphology
from . import padding, processes, selfcontact
from .padding import SolverOptions, WorldSpec
from .supertree import SharedTree, build_shared_tree

INERT_MARGIN = -1.0e4
# Sibling limbs grow from one parent 2 radii apart, so many limb pairs touch exactly in the rest pose (118 of the
# train robots' 2952 pairs). MuJoCo C (float64) decides such a contact on a distance of ~1e-9 m, below float32's
# resolution of these positions (~1.5e-8 m): unmarked, MJX switched gen-1-8's sibling contact on where MuJoCo C had
# it off (+1.0e-9 m), a 30 m/s^2 jolt at the first substep that grew to 0.10 m in 0.5 s. A robot-robot contact
# therefore counts in MJX only from 1e-7 m of penetration (its rest point moves 1e-7 m deeper). Measured on
# gen/test (docs/benchmarks.md): gap 0: 1 robot over 1e-3 m, max 0.10 m; 1e-7: none, max 4.3e-5 m; 1e-6: none,
# max 5.8e-4 m (a larger gap disagrees with MuJoCo C on real shallow contacts).
SELF_CONTACT_GAP = 1.0e-7


def self_contact_margin(geom_bodyid) -> np.ndarray:
    """What SELF_CONTACT_GAP adds to each geom's margin: -gap/2 on robot geoms, +gap/2 on world geoms (body 0), so
    robot-robot contacts count from `gap` of penetration and robot-world contacts keep their margin."""
    return np.where(np.asarray(geom_bodyid) == 0, 0.5, -0.5) * SELF_CONTACT_GAP


# ModuMorph's fixed context bounds (metamorph/envs/modules/agent.py), in the order of the 35 static features
_LIMB_BOUNDS = [
    ((-0.5, -0.45, -0.49), (0.5, 0.45, 2.04)),                              # body_pos
    ((-0.225, -0.225, -0.225), (0.225, 0.225, 0.0)),                        # body_ipos
    ((0.70710678, -0.70710678, -0.70710678, 0.0), (1.0, 0.70710678, 0.70710678, 0.0)),  # body_iquat
    ((0.70710678, -0.70710678, -0.70710678, 0.0), (1.0, 0.70710678, 0.70710678, 0.0)),  # geom_quat
    ((1.17809725,), (4.1887902,)),                                          # body_mass
    ((0.05, 0.0), (0.1, 0.22627417)),                                       # body_shape
]
_JOINT_BOUNDS = [
    ((-0.05, -0.05, 0.0), (0.05, 0.05, 0.05)),                              # jnt_pos
    ((-1.57079633, 0.0), (0.0, 1.57079633)),                                # joint_range
    ((-0.5000024, -0.5000024, -1.0), (1.0, 1.0, 1.0)),                      # joint_axis
    ((0.0,), (300.0,)),                                                     # gear
]


def _bounds(parts):
    lo = np.concatenate([np.asarray(a, np.float64) for a, _ in parts])
    hi = np.concatenate([np.asarray(b, np.float64) for _, b in parts])
    return lo, hi


LIMB_LO, LIMB_HI = _bounds(_LIMB_BOUNDS)     # 17
JOINT_LO, JOINT_HI = _bounds(_JOINT_BOUNDS)  # 9


def normalise_context(x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """ModuMorph's map: -1*(lo != hi) + 2 (x - lo) / (hi - lo + 1e-8)."""
    return -1.0 * (lo != hi) + 2.0 * (x - lo) / (hi - lo + 1e-8)


class Tables(NamedTuple):
    """Per-robot constants for the simulation (robot axis first)."""
    body_of_token: jax.Array   # (R, 12) int32 body id (slot + 1) per token
    geom_of_token: jax.Array   # (R, 12) int32
    qadr_of_action: jax.Array  # (R, 24) int32 qpos address of the joint behind an action entry (7 where masked)
    vadr_of_action: jax.Array  # (R, 24) int32 dof address (6 where masked)
    ctrl_src: jax.Array        # (R, nu) int32 action entry driving actuator a, 24 (a constant 0) where none
    real_qpos: jax.Array       # (R, nq) bool
    real_dof: jax.Array        # (R, nv) bool
    static_feat: jax.Array     # (R, 12, 52) float32 raw static features in place, time-varying entries 0
    jnt_lo: jax.Array          # (R, 24) float32 joint range low (rad) per action entry (0 where masked)
    jnt_span: jax.Array        # (R, 24) float32 hi - lo (1 where masked)
    orig_height: jax.Array     # (R,) float32 z0 - 0.2 (MetaMorph's orig_height)


@dataclasses.dataclass(frozen=True)
class StackedModel:
    robots: tuple[Morphology, ...]
    tree: SharedTree
    model: mjx.Model            # varying leaves carry a leading robot axis
    axes: mjx.Model             # same structure, leaves 0 (stacked) or None (shared)
    policy: Robots
    tables: Tables
    mj_models: tuple[mujoco.MjModel, ...]
    world: WorldSpec
    options: SolverOptions      # as used: `self_pairs` filled in when the cut was searched here
    self_contact: selfcontact.SelfPairSummary | None = None   # `.line()` for the logs
    build_seconds: tuple[tuple[str, float], ...] = ()          # where `build_stacked_model`'s time went, in order

    @property
    def num_robots(self) -> int:
        return len(self.robots)

    @property
    def names(self) -> list[str]:
        return [m.name for m in self.robots]

    def build_line(self) -> str:
        """The build's phases for the logs, e.g. "tree 3.6 s, pairs 3.4 s, compile and put (2 processes) 23.4 s,
        margins 0.7 s, stack 1.9 s, constants 0.6 s" ("" for a model built without them)."""
        return ", ".join(f"{phase} {seconds:.1f} s" for phase, seconds in self.build_seconds)

    def model_for(self, robot: jax.Array) -> mjx.Model:
        """The MJX model of one robot (a gather along the robot axis; vmap it over envs)."""
        return jax.tree_util.tree_map(lambda x, a: x if a is None else x[robot], self.model, self.axes,
                                      is_leaf=lambda x: x is None)


def _feed(h, name: str, x: Any) -> None:
    """Hash `x` under `name`: arrays by dtype, shape and bytes; dataclasses, named tuples, sequences, sets and
    mappings field by field; scalars, strings, enums and None by value."""
    if x is None or isinstance(x, (bool, int, float, str, bytes, enum.Enum, np.generic)):
        h.update(f"{name}={x!r};".encode())
    elif isinstance(x, (np.ndarray, jax.Array)):
        a = np.ascontiguousarray(np.asarray(x))
        h.update(f"{name}:{a.dtype.str}{a.shape};".encode())
        h.update(a.tobytes())
    elif dataclasses.is_dataclass(x):
        for f in dataclasses.fields(x):
            _feed(h, f"{name}.{f.name}", getattr(x, f.name))
    elif isinstance(x, tuple) and hasattr(x, "_fields"):
        for k in x._fields:
            _feed(h, f"{name}.{k}", getattr(x, k))
    elif isinstance(x, (list, tuple)):
        for i, v in enumerate(x):
            _feed(h, f"{name}[{i}]", v)
    elif isinstance(x, (set, frozenset)):
        _feed(h, name, sorted(x))
    elif isinstance(x, dict):
        for k in sorted(x):
            _feed(h, f"{name}[{k!r}]", x[k])
    else:
        raise TypeError(f"model_digest: {name} ({type(x).__name__}) has no digest: hash it as arrays or fields")


def model_digest(**parts: Any) -> str:
    """16 hex digits of SHA-256 over `parts` (each hashed exactly: a change in the last bit of a float is a change)
    and the versions of MuJoCo and MJX. Two runs whose envs give the same digest simulated the same robots with the
    same numbers; the code that steps them (MJX's functions, this package's contact rules, the env's config) is not
    in it. Runs record it per invocation (`devices.yaml`) and evaluations in their JSON, so that a resume onto
    other physics is refused and the report can tell runs of different physics apart (session 44: a code change
    framed the limbs' inertia otherwise mid-comparison, unseen until a run failed)."""
    h = hashlib.sha256()
    try:
        mjx_version = metadata.version("mujoco-mjx")
    except metadata.PackageNotFoundError:
        mjx_version = "?"
    _feed(h, "versions", (mujoco.__version__, mjx_version))
    for k in sorted(parts):
        _feed(h, k, parts[k])
    return h.hexdigest()[:16]


def is_digest(s: Any, prefix: bool = False) -> bool:
    """Whether `s` is a `model_digest` (16 lowercase hex digits), or with `prefix` its first 8 to 16 digits."""
    return (isinstance(s, str) and (8 if prefix else 16) <= len(s) <= 16
            and all(c in "0123456789abcdef" for c in s))


def _fix_static(mm: mujoco.MjModel) -> None:
    mm.body_sameframe[:] = 0
    mm.geom_sameframe[:] = 0
    mm.body_simple[:] = 0
    mm.dof_simplenum[:] = 0


def _trace_m(mm: mujoco.MjModel) -> float:
    """trace of the joint-space inertia at qpos0."""
    d = mujoco.MjData(mm)
    mujoco.mj_forward(mm, d)
    full = np.zeros((mm.nv, mm.nv))
    mujoco.mj_fullM(mm, d, full)
    return float(np.trace(full))


def compile_padded(robots: Sequence[Morphology], tree: SharedTree, world: WorldSpec,
                   options: SolverOptions) -> list[mujoco.MjModel]:
    """Compile every padded robot. The solver's tolerance is rescaled per robot: MuJoCo and MJX measure the
    solver's improvement, gradient and line-search tolerance relative to trace(M), which the locked joints'
    armature inflates by ~1e5; `tolerance * trace(M alone) / trace(M padded)` (at qpos0) gives the padded robot
    the early-exit and line-search behaviour of the robot alone."""
    return [_compile_one(tree, world, options, r, m) for r, m in enumerate(robots)]


def _compile_one(tree: SharedTree, world: WorldSpec, options: SolverOptions, r: int, m: Morphology
                 ) -> mujoco.MjModel:
    mm = mujoco.MjModel.from_xml_string(padding.padded_mjcf(m, tree, r, world, options))
    _fix_static(mm)
    mm.opt.tolerance = mm.opt.tolerance * _trace_m(compile_model(m)) / _trace_m(mm)
    return mm


#: robots from which `compile_and_put` spreads over processes: below, starting them (their JAX imports) costs more
#: than it saves
PUT_PARALLEL_FROM = 500


def compile_and_put(robots: Sequence[Morphology], tree: SharedTree, world: WorldSpec, options: SolverOptions
                    ) -> tuple[list[mujoco.MjModel], list[mjx.Model]]:
    """Each padded robot compiled (`compile_padded`) and put into MJX on the CPU with numpy leaves (`_stack` stacks
    them; in float64 under jax.enable_x64, as sim.fidelity builds its reference models). `put_model` costs ~20 ms a
    robot (JAX's dispatch per field) and compiling ~6 ms, so from `PUT_PARALLEL_FROM` robots on both run in one
    process per core, each robot compiled where it is put (the 2400 variants: ~15 s of compiling in this process
    before). The compiled models come back from the processes pickled, which leaves their `signature` 0 (the MJX
    models keep the real one); nothing reads it after `put_model`."""
    x64 = jax.dtypes.canonicalize_dtype(np.float64) == np.float64
    job = functools.partial(_compile_and_put_one, tree, world, options, x64)
    both = processes.process_map(job, list(enumerate(robots)), put_processes(len(robots)),
                                 "compiling the padded robots and MJX's put_model")
    return [mm for mm, _ in both], [mx for _, mx in both]


def put_processes(robots: int) -> int:
    """The processes `compile_and_put` spreads `robots` robots over."""
    return processes.processes_for(robots, PUT_PARALLEL_FROM)


def _compile_and_put_one(tree: SharedTree, world: WorldSpec, options: SolverOptions, x64: bool,
                         item: tuple[int, Morphology]) -> tuple[mujoco.MjModel, mjx.Model]:
    mm = _compile_one(tree, world, options, *item)
    with jax.enable_x64(x64):
        mx = mjx.put_model(mm, device=jax.local_devices(backend="cpu")[0], impl="jax")
    return mm, jax.tree_util.tree_map(np.asarray, mx)


def _stack(models: list[mjx.Model]) -> tuple[mjx.Model, mjx.Model]:
    leaves0, treedef = jax.tree_util.tree_flatten(models[0])
    all_leaves = [leaves0]
    for i, mx in enumerate(models[1:], 1):
        leaves, td = jax.tree_util.tree_flatten(mx)
        if td != treedef:
            raise RuntimeError(_diff_static(models[0], mx, i))
        all_leaves.append(leaves)
    stacked, axes = [], []
    for j in range(len(leaves0)):
        col = np.stack([np.asarray(l[j]) for l in all_leaves])
        if (col == col[:1]).all():                        # as np.array_equal of each with the first (NaN != NaN)
            stacked.append(jnp.asarray(col[0]))
            axes.append(None)
        else:
            stacked.append(jnp.asarray(col))
            axes.append(0)
    return jax.tree_util.tree_unflatten(treedef, stacked), jax.tree_util.tree_unflatten(treedef, axes)


def _diff_static(a: mjx.Model, b: mjx.Model, i: int) -> str:
    bad = []
    for f in dataclasses.fields(a):
        va, vb = getattr(a, f.name), getattr(b, f.name)
        if isinstance(va, np.ndarray) and not np.array_equal(va, vb):
            bad.append(f.name)
        elif isinstance(va, (int, float, bool)) and va != vb:
            bad.append(f.name)
    return f"padded robot {i} has a different static MJX structure than robot 0 in: {bad or 'nested fields'}"


def build_stacked_model(robots: Sequence[Morphology], world: WorldSpec = WorldSpec(),
                        options: SolverOptions = SolverOptions(), tree: SharedTree | None = None,
                        self_pair_budget: bool = True) -> StackedModel:
    """See the module docstring. `self_pair_budget`: with self-collision, collide per env only as many limb-limb
    pairs as the robot with the most has (`SolverOptions.self_pair_budget`; exact, see `limb_pair_budget`)."""
    robots = tuple(robots)
    clock = _PhaseClock()
    if tree is None:
        tree = build_shared_tree(robots)
        clock("tree")
    options, search = _with_self_pairs(robots, tree, options, budget=self_pair_budget)
    clock("pairs")
    mjm, mxs = compile_and_put(robots, tree, world, options)
    n = put_processes(len(robots))
    clock(f"compile and put ({n} process{'es' if n > 1 else ''})")
    rb = np.max(np.stack([np.asarray(mx._impl.geom_rbound_hfield) for mx in mxs]), axis=0)
    mxs = [mx.replace(_impl=mx._impl.replace(geom_rbound_hfield=rb)) for mx in mxs]
    # inert geoms: never active (margin only decides activation in MJX; collision functions ignore it), and never
    # among the closest pairs of the broad phase (MJX reads geom_rbound only there)
    # robot-robot contacts from SELF_CONTACT_GAP of penetration on; robot-world contacts as MuJoCo's
    for r, mx in enumerate(mxs):
        inert = inert_geoms(tree, r, mjm[r])
        margin = np.asarray(mx.geom_margin).copy()
        rbound = np.asarray(mx.geom_rbound).copy()
        margin += self_contact_margin(mjm[r].geom_bodyid)
        margin[inert] = INERT_MARGIN
        rbound[inert] = INERT_MARGIN
        mxs[r] = mx.replace(geom_margin=margin, geom_rbound=rbound)
    clock("margins")
    model, axes = _stack(mxs)
    clock("stack")
    policy, tables = _robot_constants(robots, tree, mjm)
    summary = _self_pair_summary(robots, tree, options, mjm[0], search)
    clock("constants")
    return StackedModel(robots=robots, tree=tree, model=model, axes=axes, policy=policy, tables=tables,
                        mj_models=tuple(mjm), world=world, options=options, self_contact=summary,
                        build_seconds=tuple(clock.phases))


class _PhaseClock:
    """Wall seconds of consecutive phases: each call closes the phase that ran since the previous call (or since
    the clock was made) under the given name."""

    def __init__(self):
        self.phases: list[tuple[str, float]] = []
        self._t = time.perf_counter()

    def __call__(self, phase: str) -> None:
        t = time.perf_counter()
        self.phases.append((phase, t - self._t))
        self._t = t


def inert_geoms(tree: SharedTree, robot: int, mm: mujoco.MjModel) -> list[int]:
    """Geom ids of the slots robot `robot` of the tree's set does not use (its inert geoms)."""
    used = {0} | set(tree.slot_of[robot])
    return [int(mm.body_geomadr[s + 1]) for s in range(tree.num_slots) if s not in used]


def _with_self_pairs(robots, tree: SharedTree, options: SolverOptions, budget: bool = False):
    """`options` with `self_pairs` filled in when self-collision and the cut are on and the caller gave none (and
    with `budget`, `self_pair_budget` = the most limb-limb pairs MJX must collide for any robot), and the search
    (or None)."""
    search = None
    if options.self_collision and options.self_collision_cut and options.self_pairs is None:
        search = selfcontact.find_slot_pairs(robots, tree)
        options = dataclasses.replace(options, self_pairs=search.kept)
    if budget and options.self_collision and options.self_pair_budget is None:
        options = dataclasses.replace(options, self_pair_budget=limb_pair_budget(tree, options))
    return options, search


def limb_pair_budget(tree: SharedTree, options: SolverOptions) -> int:
    """The most capsule-capsule pairs (two limb slots, not parent-child, not excluded) whose slots one robot uses:
    with this budget and inert geoms out of the broad phase, MJX's closest-pairs cull never drops a real pair."""
    pairs = options.self_pairs if options.self_collision_cut and options.self_pairs is not None \
        else selfcontact.candidate_slot_pairs(tree)
    limb_pairs = [(s, t) for s, t in pairs if s > 0 and t > 0]
    most = 0
    for slots in tree.slot_of:
        used = set(slots)
        most = max(most, sum(1 for s, t in limb_pairs if s in used and t in used))
    return max(most, 1)


def _self_pair_summary(robots, tree: SharedTree, options: SolverOptions, mm: mujoco.MjModel, search):
    kept = options.self_pairs if options.self_collision_cut else None
    summary = selfcontact.summarise(robots, tree, options.self_collision, kept, mm, search)
    budget = options.self_pair_budget if options.self_collision else None
    return None if summary is None else dataclasses.replace(summary, budget=budget)


def self_pair_summary(robots: Sequence[Morphology], world: WorldSpec = WorldSpec(),
                      options: SolverOptions = SolverOptions(), tree: SharedTree | None = None,
                      self_pair_budget: bool = True) -> selfcontact.SelfPairSummary:
    """The `StackedModel.self_contact` that `build_stacked_model` gives for these arguments, without building the
    MJX model (one padded robot is compiled), for tools that build their models elsewhere; `.line()` prints it.
    The per-robot search is cached, so a model built afterwards in the same process does not repeat it."""
    robots = tuple(robots)
    tree = tree or build_shared_tree(robots)
    options, search = _with_self_pairs(robots, tree, options, budget=self_pair_budget)
    mm = mujoco.MjModel.from_xml_string(padding.padded_mjcf(robots[0], tree, 0, world, options))
    return _self_pair_summary(robots, tree, options, mm, search)


def static_features(mm: mujoco.MjModel, body: int, joints: Sequence[int | None]) -> np.ndarray:
    """The 52 features of one token with the time-varying entries 0 (float64). `joints[k]` is the joint id in
    slot k or None. Reads the compiled model exactly as MetaMorph's agent.py does."""
    f = np.zeros(OBS_DIM)
    g = mm.body_geomadr[body]
    f[13:16] = mm.body_pos[body]
    f[16:19] = mm.body_ipos[body]
    f[19:23] = mm.body_iquat[body]
    f[23:27] = mm.geom_quat[g]
    f[27] = mm.body_mass[body]
    f[28:30] = mm.geom_size[g, :2]
    for k, j in enumerate(joints):
        if j is None:
            continue
        o = 30 + 11 * k
        a = j - 1                          # actuator order = joint order after the free joint
        f[o + 2:o + 5] = mm.jnt_pos[j]
        f[o + 5:o + 7] = mm.jnt_range[j]
        f[o + 7:o + 10] = mm.jnt_axis[j]
        f[o + 10] = mm.actuator_gear[a, 0]
    return f


def context_of(feat: np.ndarray, joints: Sequence[int | None]) -> np.ndarray:
    """Normalised 35-dim context of one token from its static features (missing joint slots stay 0)."""
    limb = normalise_context(feat[13:30], LIMB_LO, LIMB_HI)
    parts = [limb]
    for k in range(2):
        o = 30 + 11 * k
        if joints[k] is None:
            parts.append(np.zeros(9))
        else:
            parts.append(normalise_context(feat[o + 2:o + 11], JOINT_LO, JOINT_HI))
    return np.concatenate(parts)


def _robot_constants(robots, tree: SharedTree, mjm) -> tuple[Robots, Tables]:
    R = len(robots)
    nu = mjm[0].nu
    ctx = np.zeros((R, NUM_TOKENS, CTX_DIM), np.float32)
    node_mask = np.zeros((R, NUM_TOKENS), bool)
    act_mask = np.zeros((R, NUM_ACTIONS), bool)
    body_of_token = np.zeros((R, NUM_TOKENS), np.int32)
    geom_of_token = np.zeros((R, NUM_TOKENS), np.int32)
    qadr = np.full((R, NUM_ACTIONS), 7, np.int32)
    vadr = np.full((R, NUM_ACTIONS), 6, np.int32)
    ctrl_src = np.zeros((R, nu), np.int32)
    real_qpos = np.zeros((R, mjm[0].nq), bool)
    real_dof = np.zeros((R, mjm[0].nv), bool)
    static = np.zeros((R, NUM_TOKENS, OBS_DIM), np.float32)
    jlo = np.zeros((R, NUM_ACTIONS), np.float32)
    jspan = np.ones((R, NUM_ACTIONS), np.float32)
    orig_height = np.zeros(R, np.float32)
    for r, m in enumerate(robots):
        t = padding.pad_tables(m, tree, r, NUM_TOKENS)
        mm = mjm[r]
        node_mask[r] = t.node_mask
        act_mask[r] = t.act_mask
        body_of_token[r] = t.body_of_token
        geom_of_token[r] = mm.body_geomadr[t.body_of_token]
        ctrl_src[r] = t.ctrl_src
        real_qpos[r] = t.real_qpos
        real_dof[r] = t.real_dof
        orig_height[r] = m.height - 0.2
        for tok in range(m.num_nodes):
            joints = [int(t.jnt_of_action[2 * tok + k]) if t.act_mask[2 * tok + k] else None for k in range(2)]
            f = static_features(mm, int(t.body_of_token[tok]), joints)
            static[r, tok] = f
            ctx[r, tok] = context_of(f, joints)
            z = np.abs(f[13:30][LIMB_LO == LIMB_HI]).max()   # body_iquat's and geom_quat's z: bounds (0, 0)
            if z > 1e-9:
                raise ValueError(f"robot {m.name}, token {tok}: body_iquat / geom_quat has a z component of {z:.3g} "
                                 "where ModuMorph's context bounds (both 0) expect a capsule framed about its own "
                                 f"axis; its normalised context would be {2 * z / 1e-8:.3g} "
                                 "(unimal.mjcf.limb_inertial writes that frame)")
            for k, j in enumerate(joints):
                if j is not None:
                    qadr[r, 2 * tok + k] = mm.jnt_qposadr[j]
                    vadr[r, 2 * tok + k] = mm.jnt_dofadr[j]
                    jlo[r, 2 * tok + k] = mm.jnt_range[j, 0]
                    jspan[r, 2 * tok + k] = mm.jnt_range[j, 1] - mm.jnt_range[j, 0]
    j = jnp.asarray
    return (Robots(j(ctx), j(node_mask), j(act_mask)),
            Tables(j(body_of_token), j(geom_of_token), j(qadr), j(vadr), j(ctrl_src), j(real_qpos), j(real_dof),
                   j(static), j(jlo), j(jspan), j(orig_height)))
