"""Fidelity of the padded, stacked MJX simulation against each robot alone in MuJoCo C, on MetaMorph's floor.

Three simulations of every robot from the same start state (standing pose + U(-0.005, 0.005) noise on every
qpos/qvel entry) under the same actions (N(0, 0.9) per control step, through the env's action -> actuator table),
`steps` control steps of 4 substeps, with the same options (timestep, solver and line-search iterations,
self-collision on/off, parent-child filtering):
- `alone`:  the robot's own MJCF (`unimal.mjcf.to_mjcf`) in MuJoCo C (float64), on MetaMorph's ft floor (a box of
            half-size 100 x 100 x 1, top z = 1 in MetaMorph's world) and, with self-collision on, every non-parent
            pair;
- `padded C`: the robot padded onto the set's shared tree (locked joints, inert slots, the set's self-collision
            pair cut) in MuJoCo C (float64), on the same box;
- `padded MJX`: the same padded robot in the stacked MJX model (float32, all robots vmapped at once) on the env's
            ft floor, a plane with MuJoCo C's box-face contacts (`contact.py`);
- `alone MJX` (optional, `unpadded_mjx=True`): the robot's own MJCF in MJX (float32) on that floor, with the same
            contact rule and self-contact gap: one compilation per robot (~10 s on a CPU), hence off by default.
For each robot the largest world-position error of any body over the steps is reported three ways: `error` =
padded MJX against alone (everything we change), `padding` = padded C against alone (the padding and the pair cut
alone, same float64 engine), `mjx` = padded MJX against padded C (MJX and float32 alone, same model), and optionally
`padding_mjx` = padded MJX against alone MJX (the padding in float32, where the two programs' different rounding is
part of the difference; in float64 C that rounding is ~1e-16 and `padding` sees the padding alone), `mjx_alone` =
alone MJX against alone C (MJX and float32 without the padding) and `mjx_ulp` = alone MJX against itself started
one float32 step (ulp) away in every qpos / qvel entry: float32's own spread for that robot, the size of difference
two float32 programs that round differently can show with nothing else different. With `x64=True` both MJX
simulations run in float64 (`jax.enable_x64`): `padding_mjx` is then the padding's own error in MJX, with the two
programs' rounding at ~1e-16 as in C, and `mjx_alone` / `mjx` what MJX's algorithms differ from MuJoCo C's without
float32 (the GPU runs float32; this is a check, not a mode of the env). Every simulation runs in the
env's frame (`padding.WorldSpec.origin`: MetaMorph's world moved down 1 m, floor top at z = 0). These robots
are chaotic under tiny changes (a tiny difference at a contact onset grows into a different trajectory), so the
horizon is short (25 control steps = 0.5 s), and `sensitivity` measures each robot's own chaos: the robot alone
against itself started 1e-7 away. MuJoCo C's box-face rule switches one end's contact off when the other end's
centre dips below the face, a discontinuity that grows such differences fastest; a robot whose `sensitivity` is
as large as its `error` is an exception explained by that, not by the padding or MJX.
"""
from __future__ import annotations

import contextlib
import dataclasses
from typing import Sequence

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from ..unimal.mjcf import to_mjcf
from ..unimal.morphology import MAX_NODES, Morphology
from . import contact
from . import linalg as cholesky
from .model import INERT_MARGIN, build_stacked_model, compile_padded, inert_geoms, self_contact_margin
from .padding import SolverOptions, WorldSpec
from .supertree import SharedTree
from .terrain import Plane

FLOOR_WORLD = Plane().world()          # ft's world in MJX: a plane, top z = 0 (MetaMorph's z = 1: `origin`)
FLOOR = FLOOR_WORLD.geoms
METAMORPH_WORLD = Plane().reference_world()     # MetaMorph's ft floor box, in the env's frame
METAMORPH_FLOOR = METAMORPH_WORLD.geoms
TOLERANCE = 1e-3
MUJOCO_SOLVER = (100, 50)   # MuJoCo's default Newton and line-search iterations: MetaMorph's (MuJoCo 2.0 defaults)
PERTURBATION = 1e-7     # m / rad: the start-state nudge of the sensitivity column


def alone_model(m: Morphology, options: SolverOptions, floor: str = METAMORPH_FLOOR,
                self_gap: bool = False) -> mujoco.MjModel:
    """The robot alone in MuJoCo C, on MetaMorph's ft floor (or `floor`, top z = 0 in the env's frame, 1 in
    MetaMorph's), standing where the env starts it, with the padded model's options and contact filter; with
    `self_gap`, MJX's robot-robot contact gap too (`model.self_contact_margin`), which MetaMorph's model lacks."""
    z_offset = FLOOR_WORLD.start_pose(m.height)[0][2] - m.height
    xml = to_mjcf(m, floor=True, z_offset=z_offset, inertials=True)
    xml = xml.replace('<geom name="floor" type="plane" size="50 50 0.1" pos="0 0 0"/>', floor.strip())
    mm = mujoco.MjModel.from_xml_string(xml)
    floor = mujoco.mj_name2id(mm, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    top = mm.geom_pos[floor][2] + (mm.geom_size[floor][2] if mm.geom_type[floor] == mujoco.mjtGeom.mjGEOM_BOX else 0)
    if floor < 0 or top != z_offset:
        raise RuntimeError(f"alone_model: could not place the floor top at z = {z_offset:g} (to_mjcf's floor line "
                           "changed?)")
    robot = np.arange(mm.ngeom) != floor
    mm.geom_contype[robot] = 1
    mm.geom_conaffinity[robot] = 1 if options.self_collision else 0
    mm.opt.iterations = options.iterations
    mm.opt.ls_iterations = options.ls_iterations
    mm.opt.timestep = options.timestep
    if self_gap:
        mm.geom_margin[:] += self_contact_margin(mm.geom_bodyid)
    return mm


@dataclasses.dataclass(frozen=True)
class Result:
    name: str
    error: float           # padded MJX vs alone in MuJoCo C: max |body position error| over bodies and steps (m)
    padding: float         # padded vs alone, both in MuJoCo C
    mjx: float             # padded MJX vs padded MuJoCo C
    sensitivity: float     # alone vs alone with the start state moved by U(-1e-7, 1e-7): the robot's own chaos
    error_by_step: np.ndarray
    padding_mjx: float = float("nan")   # padded MJX vs alone MJX, both float32 (float64: x64) (unpadded_mjx=True)
    mjx_alone: float = float("nan")     # alone MJX vs alone MuJoCo C (compare(unpadded_mjx=True))
    mjx_ulp: float = float("nan")       # alone MJX vs alone MJX started one ulp of its float away (unpadded_mjx=True)
    contacts: int = -1                  # the most contacts the robot alone had at once in MuJoCo C (touching ones:
                                        # a `flat_contact_budget` at or above it changes no force)


def padded_c_models(sm, world: WorldSpec = METAMORPH_WORLD, self_gap: bool = False) -> list[mujoco.MjModel]:
    """The stacked model's padded robots compiled for MuJoCo C in `world` (MetaMorph's box floor by default), with
    the stacked model's options (self-collision pair cut included) and its inert geoms never in contact; with
    `self_gap`, MJX's robot-robot contact gap too (`model.self_contact_margin`), which MetaMorph's model lacks."""
    out = compile_padded(sm.robots, sm.tree, world, sm.options)
    for r, mm in enumerate(out):
        if self_gap:
            mm.geom_margin[:] += self_contact_margin(mm.geom_bodyid)
        mm.geom_margin[inert_geoms(sm.tree, r, mm)] = INERT_MARGIN
    return out


def converged(models: Sequence[mujoco.MjModel]) -> None:
    """Give MuJoCo C models MuJoCo's default solver iterations (MUJOCO_SOLVER, MetaMorph's): the Newton solve then
    stops at its tolerance (the train robots' substeps take at most 8 iterations), whatever MJX is given."""
    for mm in models:
        mm.opt.iterations, mm.opt.ls_iterations = MUJOCO_SOLVER


def to_padded(sm, robot: int, qpos, qvel) -> tuple[np.ndarray, np.ndarray]:
    """A state of robot `robot` alone (its own qpos / qvel layout) in the padded layout of the stacked model `sm`:
    free joint as it is, real joints at their padded addresses, locked and inert joints at qpos0 / 0."""
    entries = np.nonzero(np.asarray(sm.policy.act_mask[robot]))[0]   # token-major = the alone robot's joint order
    mm = sm.mj_models[robot]
    qp = np.asarray(mm.qpos0, np.float64).copy()
    qp[:7] = qpos[:7]
    qp[np.asarray(sm.tables.qadr_of_action[robot])[entries]] = qpos[7:]
    vp = np.zeros(mm.nv)
    vp[:6] = qvel[:6]
    vp[np.asarray(sm.tables.vadr_of_action[robot])[entries]] = qvel[6:]
    return qp, vp


def alone_mjx_model(m: Morphology, options: SolverOptions) -> mujoco.MjModel:
    """The robot alone, for MJX: its own MJCF on the env's ft floor (a plane, top z = 0, contacts by the rule of the
    enclosing `contact.floor` block) with the stacked model's self-contact gap (`model.self_contact_margin`)."""
    return alone_model(m, options, FLOOR, self_gap=True)


def _mjx_rollout(m, d, ctrls, substeps: int) -> jax.Array:
    """xpos (steps, nbody, 3) of MJX from `d` after each control step of `substeps` physics steps under `ctrls`."""
    def control(d, c):
        d = jax.lax.fori_loop(0, substeps, lambda i, dd: mjx.step(m, dd), d.replace(ctrl=c))
        return d, d.xpos
    return jax.lax.scan(control, d, ctrls)[1]


def ulp_nudge(x, rng: np.random.Generator, dtype=np.float32) -> np.ndarray:
    """`x` in `dtype` with every entry moved one step (ulp) of `dtype` up or down at random."""
    x = np.asarray(x, dtype)
    return np.where(rng.random(x.shape) < 0.5, np.nextafter(x, dtype(-np.inf)), np.nextafter(x, dtype(np.inf)))


def _run_mjx_alone(mm: mujoco.MjModel, starts, ctrls, substeps: int, bodies, floor_contacts: str,
                   matmul_precision: str, compiler_options: dict | None, dtype=jnp.float32,
                   linalg: str = cholesky.DEFAULT) -> list[np.ndarray]:
    """Body positions (steps, len(bodies), 3) of the robot alone in MJX (float32, or `dtype` under
    `jax.enable_x64`), as `_run_c`, from each (qpos, qvel) of `starts` (one compilation)."""
    mx = mjx.put_model(mm, impl="jax")
    d0 = mjx.make_data(mx, impl="jax")

    def run(q, v, a):
        return _mjx_rollout(mx, d0.replace(qpos=q, qvel=v), a, substeps)[:, bodies]

    def args(q, v):
        return jnp.asarray(q, dtype), jnp.asarray(v, dtype), jnp.asarray(ctrls, dtype)
    with contact.floor(floor_contacts), jax.default_matmul_precision(matmul_precision), cholesky.use(linalg):
        f = jax.jit(run, compiler_options=compiler_options).lower(*args(*starts[0])).compile()
    return [np.asarray(f(*args(q, v)), np.float64) for q, v in starts]


def _run_c(mm: mujoco.MjModel, qpos, qvel, ctrls, substeps: int, bodies) -> tuple[np.ndarray, int]:
    """Body positions (steps, len(bodies), 3) of MuJoCo C after each control step (at the start of the last
    substep, where MJX leaves xpos too), and the most contacts it had at once (MuJoCo C keeps only those that
    touch: within the geoms' margin, 0 here)."""
    d = mujoco.MjData(mm)
    d.qpos[:], d.qvel[:] = qpos, qvel
    out = np.zeros((len(ctrls), len(bodies), 3))
    most = 0
    for t, c in enumerate(ctrls):
        d.ctrl[:] = c
        for _ in range(substeps):
            mujoco.mj_step(mm, d)
            most = max(most, d.ncon)
        out[t] = d.xpos[bodies]
    return out, most


def summary(values) -> dict:
    """median, 99th percentile and max of a list of errors (m); NaNs (robots not measured) are left out."""
    v = np.asarray(values, np.float64)
    v = v[~np.isnan(v)]
    if not v.size:
        return {"median": float("nan"), "p99": float("nan"), "max": float("nan")}
    return {"median": float(np.median(v)), "p99": float(np.percentile(v, 99)), "max": float(v.max())}


def compare(robots: Sequence[Morphology], options: SolverOptions = SolverOptions(), steps: int = 25,
            substeps: int = 4, seed: int = 0, tree: SharedTree | None = None,
            compiler_options: dict | None = None, floor_contacts: str = "box",
            matmul_precision: str = "highest", unpadded_mjx: bool = False, x64: bool = False,
            alone: range | None = None, c_gap: bool = False, c_defaults: bool = False,
            linalg: str = cholesky.DEFAULT) -> list[Result]:
    """Compare every robot (see the module docstring). `floor_contacts`: "box" (MetaMorph's box floor in MuJoCo C,
    its rule in MJX) or "plane" (a plane in MuJoCo C, MuJoCo C's plane rule in MJX); `matmul_precision`: MJX's
    (the env's `EnvConfig.matmul_precision`; it matters on GPUs with TF32); `unpadded_mjx`: also run each robot
    alone in MJX (Result.padding_mjx); `x64`: MJX in float64 (the stacked model is built inside, so it is float64
    too); `alone`: with unpadded_mjx, only the robots of these indices run alone in MJX (one compilation each; the
    others' MJX-alone fields are NaN), each with exactly the start, actions and nudges of a run over all robots, so
    a large set can be checked in slices; `c_gap`: MuJoCo C (alone and padded) with MJX's robot-robot contact gap
    too, so that only the engines differ (a robot over the tolerance without it but not with it is the gap's: a
    limb-limb contact within 1e-7 m of touching, decided one way by MuJoCo C and the other by the gap);
    `c_defaults`: MuJoCo C at MuJoCo's default solver iterations (`converged`), MetaMorph's physics, while MJX runs
    `options`' (the env's): the whole of our physics against the paper's, the solver's truncation included.
    `linalg`: MJX's Cholesky (the env's `EnvConfig.linalg`: auto | jax | pallas; sim/linalg.py)."""
    cholesky.check(linalg)
    if floor_contacts not in ("box", "plane"):
        raise ValueError(f"floor_contacts={floor_contacts!r}: expected 'box' or 'plane'")
    with jax.enable_x64(True) if x64 else contextlib.nullcontext():
        return _compare(tuple(robots), options, steps, substeps, seed, tree, compiler_options, floor_contacts,
                        matmul_precision, unpadded_mjx, jnp.float64 if x64 else jnp.float32,
                        range(len(robots)) if alone is None else alone, c_gap, c_defaults, linalg)


def _compare(robots, options, steps, substeps, seed, tree, compiler_options, floor_contacts, matmul_precision,
             unpadded_mjx, dtype, alone_robots, c_gap, c_defaults, linalg) -> list[Result]:
    c_floor = METAMORPH_FLOOR if floor_contacts == "box" else FLOOR
    np_dtype = np.dtype(dtype).type          # the MJX float, for the ulp nudge
    sm = build_stacked_model(robots, FLOOR_WORLD, options, tree=tree)
    R = len(robots)
    nq, nv = sm.mj_models[0].nq, sm.mj_models[0].nv
    rng = np.random.default_rng(seed)
    # start states and actions, in the alone robot's layout
    starts, actions, alone = [], [], []
    for m in robots:
        mm = alone_model(m, options, c_floor, self_gap=c_gap)
        if c_defaults:
            converged([mm])
        alone.append(mm)
        q = mm.qpos0 + rng.uniform(-0.005, 0.005, mm.nq)
        v = rng.uniform(-0.005, 0.005, mm.nv)
        a = rng.normal(0.0, 0.9, (steps, mm.nu))
        starts.append((q, v))
        actions.append(a)
    tab = jax.tree_util.tree_map(np.asarray, sm.tables)
    pol = jax.tree_util.tree_map(np.asarray, sm.policy)
    # padded layout
    qpos = np.zeros((R, nq))
    qvel = np.zeros((R, nv))
    act24 = np.zeros((R, steps, 2 * MAX_NODES))
    bodies = np.zeros((R, MAX_NODES), np.int32)
    for r, m in enumerate(robots):
        qpos[r], qvel[r] = to_padded(sm, r, *starts[r])
        entries = np.nonzero(pol.act_mask[r])[0]          # token-major = the alone robot's actuator order
        act24[r][:, entries] = actions[r]
        bodies[r] = tab.body_of_token[r]

    template = mjx.make_data(sm.model_for(0), impl="jax")

    def run(robot, q, v, a24, ctrl_src):
        ctrls = jnp.concatenate([jnp.clip(a24, -1, 1), jnp.zeros((a24.shape[0], 1))], axis=1)[:, ctrl_src]
        return _mjx_rollout(sm.model_for(robot), template.replace(qpos=q, qvel=v), ctrls, substeps)

    args = (jnp.arange(R), jnp.asarray(qpos, dtype), jnp.asarray(qvel, dtype),
            jnp.asarray(act24, dtype), jnp.asarray(tab.ctrl_src))
    # the floor rule, the matmul precision and the Cholesky are chosen while tracing
    with contact.floor(floor_contacts), jax.default_matmul_precision(matmul_precision), cholesky.use(linalg):
        f = jax.jit(jax.vmap(run), compiler_options=compiler_options).lower(*args).compile()
    xs = np.asarray(f(*args))
    padded_c = padded_c_models(sm, dataclasses.replace(FLOOR_WORLD, geoms=c_floor), c_gap)
    if c_defaults:
        converged(padded_c)
    out = []
    for r, m in enumerate(robots):
        real = bodies[r, :m.num_nodes]
        x_alone, contacts = _run_c(alone[r], *starts[r], actions[r], substeps, np.arange(1, 1 + m.num_nodes))
        ctrl = np.concatenate([np.clip(act24[r], -1, 1), np.zeros((steps, 1))], axis=1)[:, tab.ctrl_src[r]]
        x_padded, _ = _run_c(padded_c[r], qpos[r], qvel[r], ctrl, substeps, real)
        x_mjx = xs[r][:, real]
        q, v = starts[r]
        nudge = rng.uniform(-PERTURBATION, PERTURBATION, q.shape)
        x_nudged, _ = _run_c(alone[r], q + nudge, v, actions[r], substeps, np.arange(1, 1 + m.num_nodes))
        err = np.abs(x_mjx - x_alone).max(axis=(1, 2))
        padding_mjx = mjx_alone = mjx_ulp = float("nan")
        if unpadded_mjx:
            ulp = (ulp_nudge(q, rng, np_dtype), ulp_nudge(v, rng, np_dtype))   # drawn for every robot: same stream
        if unpadded_mjx and r in alone_robots:
            x_alone_mjx, x_ulp = _run_mjx_alone(
                alone_mjx_model(m, options), [(q, v), ulp], actions[r], substeps, np.arange(1, 1 + m.num_nodes),
                floor_contacts, matmul_precision, compiler_options, dtype, linalg)
            padding_mjx = float(np.abs(x_mjx - x_alone_mjx).max())
            mjx_alone = float(np.abs(x_alone_mjx - x_alone).max())
            mjx_ulp = float(np.abs(x_ulp - x_alone_mjx).max())
        out.append(Result(m.name, float(err.max()), float(np.abs(x_padded - x_alone).max()),
                          float(np.abs(x_mjx - x_padded).max()), float(np.abs(x_nudged - x_alone).max()), err,
                          padding_mjx, mjx_alone, mjx_ulp, contacts))
    return out


@dataclasses.dataclass
class TaskResult:
    name: str
    steps: np.ndarray       # per control step: body-position error (m), padded MJX against padded MuJoCo C
    ulp_steps: np.ndarray   # per control step: padded MJX against itself started one ulp away
    step_steps: np.ndarray  # per control step: error of that step alone, MuJoCo C restarted from MJX's state
    ncon: np.ndarray        # (steps, 2, substeps) MuJoCo C's contacts after each substep: [:, 0] its own run, [:, 1]
                            # the restart from MJX's state
    contacts: list | None = None   # traced robots only: [step][run 0 / restart 1][substep] = [(distance, geom,
                                   # geom)], MuJoCo C's contacts by geom name, deepest first

    @property
    def mjx(self) -> float:
        """Max body-position error (m), padded MJX against padded MuJoCo C on MetaMorph's ground."""
        return float(self.steps.max())

    @property
    def mjx_ulp(self) -> float:
        """Max body-position difference, padded MJX against itself started one ulp away."""
        return float(self.ulp_steps.max())

    @property
    def mjx_step(self) -> float:
        """Max body-position error of one control step, MuJoCo C restarted from MJX's state."""
        return float(self.step_steps.max())


def compare_task(robots: Sequence[Morphology], task: str, options: SolverOptions = SolverOptions(),
                 steps: int = 25, seed: int = 0, trace: Sequence[str] = (), x64: bool = False,
                 c_gap: bool = False, c_defaults: bool = False, **env_options) -> list[TaskResult]:
    """The tasks beyond ft (incline, csr, obstacle): every robot in the env's padded MJX model against the same padded
    model in MuJoCo C (float64) on MetaMorph's ground (`Terrain.reference_world`: the incline's slab box, the height
    fields' patch), from the env's own reset state (a generated terrain) under N(0, 0.9) actions. On csr and
    obstacle both get, before each control step, the height-field patch the env centres under their own torso
    (`terrain.patch`), so the comparison is MJX's height-field collider (the env's `hfield_contacts` rule,
    hfield_contact.py), its contact budget and float32 against MuJoCo C's; on the incline it is the floor rule
    (contact.py) and float32 against MuJoCo C's box. `env_options`: further EnvConfig options (hfield_contacts,
    hfield_contacts_per_geom, contact_budget, flat_contact_budget, linalg). Body positions are compared through
    MuJoCo C's kinematics of both states. `mjx_ulp`: the same MJX run started with every qpos / qvel entry one
    float32 step (ulp) away, against the run itself: float32's own spread on that trajectory, the size of
    difference rounding alone makes (a chaotic trajectory shows a gap to MuJoCo C as large as this spread).
    `mjx_step`: MuJoCo C
    restarted from MJX's state (qpos, qvel, the solver's warm start) before each control step and run that one
    step, against MJX's next state: the physics compared without the trajectory's amplification of float32's
    per-step error. `trace`: names of robots whose MuJoCo C contacts (run and restart, every substep) are kept in
    `TaskResult.contacts`, to see what a large step error was: a contact that one state makes and the other, a
    hair away, does not (a contact within ~1e-6 m of touching, which float32 rounding decides, changes a step by
    as much as the body's speed times a substep). `x64`: the env in float64 (`jax.enable_x64`; the env and its
    model are built inside), so MJX's float32 is out of the comparison and `mjx_ulp` is float64's own spread.
    `c_gap`: MuJoCo C with MJX's robot-robot contact gap too (`model.SELF_CONTACT_GAP`, 1e-7 m; MetaMorph's model
    has none), so that only the engines differ: in float64 the step errors then show MJX's own difference.
    `c_defaults`: MuJoCo C at MuJoCo's default solver iterations (`converged`), MetaMorph's, as in `compare`."""
    with jax.enable_x64(True) if x64 else contextlib.nullcontext():
        return _compare_task(tuple(robots), task, options, steps, seed, tuple(trace),
                             np.float64 if x64 else np.float32, c_gap, c_defaults, env_options)


def _compare_task(robots, task, options, steps, seed, trace, dtype, c_gap, c_defaults,
                  env_options) -> list[TaskResult]:
    from .env import EnvConfig, UnimalEnv
    env = UnimalEnv(robots, EnvConfig(task=task, iterations=options.iterations, ls_iterations=options.ls_iterations,
                                      self_collision=options.self_collision, **env_options))
    if env.task.name == "ft":
        raise ValueError("compare_task: ft is checked by compare() (each robot alone too)")
    sm, R = env.sm, len(robots)
    rng = np.random.default_rng(seed)
    keys = jax.random.split(jax.random.PRNGKey(seed), R)
    start = jax.jit(jax.vmap(env.reset))(keys, jnp.arange(R))
    act_mask = np.asarray(sm.policy.act_mask)
    actions = np.where(act_mask[:, None], rng.normal(0.0, 0.9, (R, steps, act_mask.shape[1])), 0.0)

    def run(state, acts):
        def body(s, a):
            s = env.step(s, a)
            return s, s.physics
        return jax.lax.scan(body, state, acts)[1]
    run_all = jax.jit(jax.vmap(run))
    physics = jax.tree_util.tree_map(lambda x: np.asarray(x, np.float64),
                                     run_all(start, jnp.asarray(actions, dtype)))    # (R, steps, ...) each
    nudge = lambda x: jnp.asarray(ulp_nudge(x, rng, dtype))                       # noqa: E731
    nudged = start._replace(physics=start.physics._replace(qpos=nudge(start.physics.qpos),
                                                           qvel=nudge(start.physics.qvel)))
    qpos_ulp = np.asarray(run_all(nudged, jnp.asarray(actions, dtype)).qpos, np.float64)

    hfield = env.terrain.uses_hfield
    patch = jax.jit(env.terrain.patch) if hfield else None
    tab = jax.tree_util.tree_map(np.asarray, sm.tables)
    out = []
    references = padded_c_models(sm, env.terrain.reference_world(), c_gap)
    if c_defaults:
        converged(references)
    for r, (m, mm) in enumerate(zip(robots, references)):
        ts = jax.tree_util.tree_map(lambda x: x[r], start.episode.terrain)
        first = jax.tree_util.tree_map(lambda x: np.asarray(x[r], np.float64), start.physics)
        d, ds, dk = mujoco.MjData(mm), mujoco.MjData(mm), mujoco.MjData(mm)   # the run, the restarts, kinematics
        d.qpos[:], d.qvel[:] = first.qpos, first.qvel
        bodies = tab.body_of_token[r][:m.num_nodes]
        errs, spread, step_errs = np.zeros(steps), np.zeros(steps), np.zeros(steps)
        ncon = np.zeros((steps, 2, env.config.substeps), np.int32)
        traced = [] if m.name in trace else None

        def xpos(qpos):
            dk.qpos[:] = qpos
            mujoco.mj_kinematics(mm, dk)
            return dk.xpos[bodies].copy()

        def control_step(dd, ctrl, counts, log):
            if hfield:                                   # the patch centred under this state's own torso
                data, pos = patch(ts, jnp.asarray(dd.qpos[0], dtype), jnp.asarray(dd.qpos[1], dtype))
                mm.hfield_data[:] = np.asarray(data, np.float64)
                mm.geom_pos[env._hgeom] = np.asarray(pos, np.float64)
            dd.ctrl[:] = ctrl
            for k in range(env.config.substeps):
                mujoco.mj_step(mm, dd)
                counts[k] = dd.ncon
                if log is not None:
                    log.append(sorted((float(dist), mm.geom(g[0]).name, mm.geom(g[1]).name)
                                      for dist, g in zip(dd.contact.dist[:dd.ncon], dd.contact.geom[:dd.ncon])))
            return xpos(dd.qpos)
        for t in range(steps):
            ctrl = np.concatenate([np.clip(actions[r, t], -1, 1), [0.0]])[tab.ctrl_src[r]]
            before = first if t == 0 else jax.tree_util.tree_map(lambda x: x[r, t - 1], physics)
            ds.qpos[:], ds.qvel[:], ds.qacc_warmstart[:] = before.qpos, before.qvel, before.qacc_warmstart
            logs = ([], []) if traced is not None else (None, None)
            x_restart = control_step(ds, ctrl, ncon[t, 1], logs[1])
            x_c = control_step(d, ctrl, ncon[t, 0], logs[0])
            if traced is not None:
                traced.append(logs)
            x_mjx = xpos(physics.qpos[r, t])
            errs[t] = np.abs(x_mjx - x_c).max()
            step_errs[t] = np.abs(x_mjx - x_restart).max()
            spread[t] = np.abs(xpos(qpos_ulp[r, t]) - x_mjx).max()
        out.append(TaskResult(m.name, errs, spread, step_errs, ncon, traced))
    return out
