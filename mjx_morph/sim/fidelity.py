"""Fidelity of the padded, stacked MJX simulation against each robot alone in MuJoCo C.

For every robot: the robot alone (its own MJCF, `unimal.mjcf.to_mjcf`) on a plane at z = 1 in MuJoCo C (float64),
and the same robot padded onto the set's shared tree inside the stacked MJX model (float32, all robots of the set
vmapped at once), with the same options (timestep, solver and line-search iterations, self-collision on/off), the
same start state (standing pose + U(-0.005, 0.005) noise on every qpos/qvel entry) and the same actions
(N(0, 0.9) per control step, applied through the env's action -> actuator table). Over `steps` control steps of
4 substeps the largest world-position error of any body is reported. These robots are chaotic under tiny
parameter changes (a tiny difference at a contact onset grows into a different trajectory), so the horizon is
short (25 control steps = 0.5 s). MJX uses MuJoCo C's plane-capsule contact frames (`contact.py`, installed when
`mjx_morph.sim` is imported).
"""
from __future__ import annotations

import dataclasses
from typing import Sequence

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from ..unimal.mjcf import to_mjcf
from ..unimal.morphology import MAX_NODES, Morphology
from .model import build_stacked_model
from .padding import SolverOptions, WorldSpec
from .supertree import SharedTree
from .terrain import Plane

FLOOR = Plane().world().geoms          # ft's floor: a plane, top z = 1
TOLERANCE = 1e-3


def alone_model(m: Morphology, options: SolverOptions) -> mujoco.MjModel:
    """The robot alone in MuJoCo C, on a plane at z = 1, with the padded model's options and contact filter."""
    xml = to_mjcf(m, floor=True, z_offset=1.0)
    xml = xml.replace('<geom name="floor" type="plane" size="50 50 0.1" pos="0 0 0"/>', FLOOR.strip())
    mm = mujoco.MjModel.from_xml_string(xml)
    floor = mujoco.mj_name2id(mm, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    if floor < 0 or mm.geom_pos[floor][2] != 1.0:
        raise RuntimeError("alone_model: could not place the floor at z = 1 (to_mjcf's floor line changed?)")
    robot = np.arange(mm.ngeom) != floor
    mm.geom_contype[robot] = 1
    mm.geom_conaffinity[robot] = 1 if options.self_collision else 0
    mm.opt.iterations = options.iterations
    mm.opt.ls_iterations = options.ls_iterations
    mm.opt.timestep = options.timestep
    return mm


@dataclasses.dataclass(frozen=True)
class Result:
    name: str
    error: float           # max |body position error| over bodies and control steps (m)
    error_by_step: np.ndarray


def compare(robots: Sequence[Morphology], options: SolverOptions = SolverOptions(), steps: int = 25,
            substeps: int = 4, seed: int = 0, tree: SharedTree | None = None,
            compiler_options: dict | None = None) -> list[Result]:
    robots = tuple(robots)
    sm = build_stacked_model(robots, WorldSpec(geoms=FLOOR), options, tree=tree)
    R = len(robots)
    nq, nv = sm.mj_models[0].nq, sm.mj_models[0].nv
    rng = np.random.default_rng(seed)
    # start states and actions, in the alone robot's layout
    starts, actions, alone = [], [], []
    for m in robots:
        mm = alone_model(m, options)
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
        q, v = starts[r]
        entries = np.nonzero(pol.act_mask[r])[0]          # token-major = the alone robot's actuator order
        qpos[r] = sm.mj_models[r].qpos0
        qpos[r, :7] = q[:7]
        qpos[r, tab.qadr_of_action[r, entries]] = q[7:]
        qvel[r, :6] = v[:6]
        qvel[r, tab.vadr_of_action[r, entries]] = v[6:]
        act24[r][:, entries] = actions[r]
        bodies[r] = tab.body_of_token[r]

    template = mjx.make_data(sm.model_for(0), impl="jax")

    def run(robot, q, v, a24, ctrl_src):
        m = sm.model_for(robot)
        d = template.replace(qpos=q, qvel=v)

        def control(d, a):
            ctrl = jnp.concatenate([jnp.clip(a, -1, 1), jnp.zeros(1)])[ctrl_src]
            d = d.replace(ctrl=ctrl)
            d = jax.lax.fori_loop(0, substeps, lambda i, dd: mjx.step(m, dd), d)
            return d, d.xpos
        _, xs = jax.lax.scan(control, d, a24)
        return xs

    f = jax.jit(jax.vmap(run), compiler_options=compiler_options)
    xs = np.asarray(f(jnp.arange(R), jnp.asarray(qpos, jnp.float32), jnp.asarray(qvel, jnp.float32),
                      jnp.asarray(act24, jnp.float32), jnp.asarray(tab.ctrl_src)))
    out = []
    for r, m in enumerate(robots):
        mm = alone[r]
        d = mujoco.MjData(mm)
        d.qpos[:], d.qvel[:] = starts[r]
        errs = np.zeros(steps)
        for t in range(steps):
            d.ctrl[:] = actions[r][t]
            for _ in range(substeps):
                mujoco.mj_step(mm, d)
            # MuJoCo C and MJX both leave xpos at the start of the last substep
            mjx_pos = xs[r, t, bodies[r, :m.num_nodes]]
            errs[t] = np.abs(mjx_pos - d.xpos[1:1 + m.num_nodes]).max()
        out.append(Result(m.name, float(errs.max()), errs))
    return out
