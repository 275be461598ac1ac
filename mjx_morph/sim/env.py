"""The UNIMAL environment: pure `reset` / `step` functions over one stacked MJX model, in two layers.

    env = make_env("unimal100/train", "ft")                  # or a RobotSet, a list of Morphology, a path
    sampler = sampling.init(env.num_robots, "balanced")
    state = env.init(key, num_envs, sampler)                  # batched reset, robots drawn from the sampler
    state = env.vstep(state, action, sampler)                 # = jax.vmap(env.step, (0, 0, None))
    # inside the PPO: lax.scan over env.vstep; sampler = sampling.update(sampler, ...) once per iteration

`UnimalEnv` is the task (single-env functions; vmap them):
    reset(key, robot) -> EnvState         the robot's start pose + U(-0.005, 0.005) noise on every real qpos and
                                          qvel entry (quaternion not re-normalised, as MetaMorph), a new terrain
    step(state, action) -> EnvState       one control step, the transition only (no reset):
        1. the action (24,) is masked, clamped to [-1, 1] (MuJoCo's ctrlrange) and scattered to the actuators;
        2. for csr/obstacle the height-field patch is re-centred under the torso;
        3. 4 MJX physics substeps (control dt 0.02 s);
        4. reward, fall / side-limit termination, the 1000-step time limit, and the instability check: a NaN or
           inf anywhere in qpos/qvel or the body kinematics, |qvel| > max_qvel, or the torso farther than 1e4 m
           ends the episode with unstable = True (counted in the episode stats, not as a fall, reward 0,
           `truncated` = True so that PPO does not treat it as a true terminal); nothing of that state reaches the
           observation (the physics state is zeroed).
`make_env` wraps it in `wrappers.AutoReset` (the `Env` that training and evaluation use): its `step(state, action,
sampler=None)` at once resets an env whose episode ended into a robot drawn from `sampler.probs` (uniform without
a sampler) with a new terrain, so the returned observation is the new episode's first one, as in MetaMorph's
vectorised envs; it adds the batched `vreset`, `vstep` and `init`.

EnvState groups the physics (qpos, qvel, qacc_warmstart), the running episode (robot, t, return, torso x, terrain
state), the observation, and the transition just taken: `reward`, `done`, `truncated` and `ended`, the statistics
of the episode that ended at this step (return, length, robot, fell, out_of_bounds, timeout, unstable; meaningful
where `done`).

Options (EnvConfig), each a documented deviation where it differs from MetaMorph: solver iterations (a cap of 16,
MuJoCo's default 100) and line-search iterations (8, default 50). The Newton solve stops at MuJoCo's tolerance before
16 in every check run (ft and incline take at most 8, csr 12), so it solves what MetaMorph's MuJoCo C at its defaults
solves (`experiments.check_sim SET c_defaults=true`: MJX at 16 / 8 within float32's spread of MuJoCo C at 100 / 50;
line search 50 changes nothing). Until session 43 the cap was 5, chosen against MuJoCo C run at 5 too: the solve
stopped unconverged, and against MetaMorph's converged MuJoCo C 41 of the 100 train robots ended over 1e-3 m apart
within 0.5 s on ft (93 on csr), 12 within one control step (docs/benchmarks.md, session 43); `env.iterations=5`
keeps that physics, which every run before session 43 trained on. Self-collision (on, as MetaMorph, with the candidate
pairs cut to those some robot of the set can make touch, `selfcontact.py`); physics in
float32 with float32 matmuls (`matmul_precision="highest"`: JAX's default would round matmul inputs to TF32 on
recent NVIDIA GPUs; MetaMorph float64); the ft / incline floor is a plane whose capsule contacts are those
MuJoCo C makes against MetaMorph's box floor (`floor_contacts="box"`, `contact.py`); csr / obstacle height-field
contacts are MuJoCo C's (`hfield_contacts="mujoco"`, `hfield_contact.py`: one per penetrated prism, at most
`hfield_contacts_per_geom` = 32 per geom, tested exactly only on the `hfield_candidates` = 96 prisms per group of
pairs that a cheap bound says can touch) and MJX keeps at most `contact_budget` = 64 contacts per env on those
tasks, the deepest (MuJoCo C has no such cap; none of 100 train robots x 3 s of random actions made more than 44).
On ft / incline MJX keeps the `flat_contact_budget` = 32 deepest of an env's 80-101 contact slots, which changes no
force while at most 32 contacts touch (MuJoCo C: at most 12; up to float rounding, the other slots' rows carry none)
and shrinks the solver's constraint rows, the rollout's largest cost. Contacts otherwise as MetaMorph: condim 3,
friction 0.7, pyramidal cone, Newton solver, Euler integrator, parent-child filtering, no exclude pairs.
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
from typing import Any, Iterator, List, NamedTuple, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from ..layout import NUM_ACTIONS, Obs, Robots, context_mask
from ..unimal.morphology import Morphology
from ..unimal.sets import RobotSet, load_set
from . import contact, hfield_contact, linalg, observation, reward, terrain
from .model import StackedModel, Tables, build_stacked_model, model_digest
from .padding import SolverOptions
from .tasks import EPISODE_LENGTH, FRAME_SKIP, RESET_NOISE, Task, get_task
from .wrappers import AutoReset


@dataclasses.dataclass
class EnvConfig:
    """The task and the simulator's options: the one home of their defaults (`experiments.run env=<task>
    env.<key>=...`). Deviations from MetaMorph are documented at the top of this module."""
    task: str = "ft"                # ft | incline | csr | obstacle (sim/tasks.py)
    iterations: int = 16            # Newton iterations at most (MuJoCo default 100; converged before 16)
    ls_iterations: int = 8          # line-search iterations (MuJoCo default 50)
    self_collision: bool = True     # as MetaMorph (parent-child pairs filtered)
    self_collision_cut: bool = True # check only the slot pairs some robot can make touch (selfcontact.py)
    self_pair_budget: bool = True   # collide per env only as many limb pairs as the robot with the most has
                                    # (exact: inert pairs are never picked; padding.SolverOptions)
    episode_length: int = EPISODE_LENGTH   # control steps (20 s)
    substeps: int = FRAME_SKIP
    reset_noise: float = RESET_NOISE
    max_qvel: float = 1.0e3         # instability threshold on any |qvel| entry
    unroll_substeps: bool = False   # Python-unroll the substeps instead of a fori_loop
    floor_contacts: str = "box"     # ft / incline floor-capsule contacts: "box" (MuJoCo C against MetaMorph's box
                                    # floor), "plane" (MuJoCo C's plane) or "mjx" (MJX's own); contact.py
    hfield_contacts: str = "mujoco" # csr / obstacle height-field contacts of spheres and capsules: "mujoco" (MuJoCo
                                    # C's, one per penetrated prism) or "mjx" (MJX's own, 4 per geom);
                                    # hfield_contact.py
    hfield_contacts_per_geom: int = hfield_contact.DEFAULT_PER_GEOM   # "mujoco": contact slots per (height
                                    # field, geom) pair, 32 (the deepest are kept beyond; MuJoCo C keeps up to 50)
    hfield_candidates: int = hfield_contact.DEFAULT_CANDIDATES   # "mujoco": prisms per group of (height
                                    # field, geom) pairs tested exactly, 96, those of lowest bound
                                    # (hfield_contact.hfield_group; the train set's groups had at most 72 that can
                                    # touch); 0: every prism of every geom's window
    contact_budget: int = 64        # csr / obstacle: MJX keeps at most this many contacts per env, the deepest
                                    # (MuJoCo C: no such cap); 0: every contact slot (padding.SolverOptions)
    flat_contact_budget: int = 32   # ft / incline: the same cap (0: every contact slot, the default before
                                    # session 35). With self-collision an env has 80-101 contact slots, and MuJoCo C
                                    # had at most 12 touching at once in check_sim's runs of the train set: a cap
                                    # above that changes no force (check_sim: the same error per robot with 16 and
                                    # 32) and shrinks the solver; 32 ran the rollout fastest of 0 / 16 / 32 / 64 on
                                    # an H200 (docs/benchmarks.md, "Session 35")

    def contact_cap(self, uses_hfield: bool) -> int | None:
        """The contact budget the env applies on a task with or without height fields (None: every slot)."""
        budget = self.contact_budget if uses_hfield else self.flat_contact_budget
        if budget < 0:
            key = "contact_budget" if uses_hfield else "flat_contact_budget"
            raise ValueError(f"env.{key}={budget}: expected a count of contacts per env (0: no budget)")
        return budget or None
    context_features: Optional[List[str]] = None   # None: all context features; else only these groups of
                                                   # mjx_morph.layout.CONTEXT_GROUPS, the others zeroed
    matmul_precision: str = "highest"   # JAX matmul precision of the physics: "highest" (float32, as MuJoCo's
                                        # arithmetic needs) or "default" (JAX's: TF32 on recent NVIDIA GPUs,
                                        # which took 45 of 100 train robots over 1 mm from MuJoCo C in 0.5 s on
                                        # an H200, none with "highest": docs/benchmarks.md, session 42)
    linalg: str = "auto"            # MJX's Cholesky factor / solve (Newton Hessian, mass matrix): "auto" (the
                                    # default: "pallas" on a GPU, "jax" elsewhere), "jax" (JAX's own: cuSOLVER /
                                    # cuBLAS on a GPU) or "pallas" (sim/gpu_linalg.py's fused kernels); what each
                                    # is and was measured to do: sim/linalg.py. Chosen while the env's step is
                                    # traced; arithmetic only, so outside the model digest, and a resume may change it


class Physics(NamedTuple):
    """The MJX state carried from one control step to the next (padded layout of the shared tree)."""
    qpos: jax.Array
    qvel: jax.Array
    qacc_warmstart: jax.Array


class Episode(NamedTuple):
    """The running episode."""
    robot: jax.Array            # () int32
    t: jax.Array                # () int32 control steps taken in this episode
    ret: jax.Array              # return so far
    torso_x: jax.Array          # torso x as last observed (reward baseline)
    terrain: Any                # the episode's terrain state (terrain.NoTerrain / Corridor / Obstacles)


class EpisodeStats(NamedTuple):
    """Statistics of the episode that ended at this step (meaningful where `EnvState.done`)."""
    ret: jax.Array
    length: jax.Array
    robot: jax.Array
    fell: jax.Array
    out_of_bounds: jax.Array
    timeout: jax.Array
    unstable: jax.Array


class EnvState(NamedTuple):
    physics: Physics
    episode: Episode
    obs: Obs
    reward: jax.Array           # raw reward of the last transition
    done: jax.Array             # the last transition ended an episode
    truncated: jax.Array        # ... by the time limit or instability (not a true terminal)
    ended: EpisodeStats         # the episode the last transition ended (meaningful where `done`)
    key: jax.Array


def _no_stats() -> EpisodeStats:
    z = jnp.float32(0.0)
    f = jnp.asarray(False)
    return EpisodeStats(ret=z, length=jnp.int32(0), robot=jnp.int32(0), fell=f, out_of_bounds=f, timeout=f,
                        unstable=f)


def _in_physics(method):
    """Trace the method under the physics' matmul precision and contact rules (`UnimalEnv.physics`)."""
    @functools.wraps(method)
    def wrapped(self, *args, **kwargs):
        with self.physics():
            return method(self, *args, **kwargs)
    return wrapped


class UnimalEnv:
    """The task: the stacked model, its terrain and the static configuration; all methods are pure and jit-able.
    `step` returns the transition without resetting (see `wrappers.AutoReset`)."""

    def __init__(self, robots: Sequence[Morphology], config: EnvConfig = EnvConfig()):
        self.config = config
        self.task: Task = get_task(config.task)
        contact.check_rule(config.floor_contacts)
        hfield_contact.check_rule(config.hfield_contacts, config.hfield_contacts_per_geom,
                                  config.hfield_candidates)
        if config.matmul_precision not in ("highest", "default"):
            raise ValueError(f"env.matmul_precision={config.matmul_precision!r}: expected highest or default")
        linalg.check(config.linalg)
        self.morphologies = tuple(robots)
        self.terrain: terrain.Terrain = terrain.for_task(self.task, self.morphologies)
        budget = config.contact_cap(self.terrain.uses_hfield)
        opts = SolverOptions(iterations=config.iterations, ls_iterations=config.ls_iterations,
                             self_collision=config.self_collision, self_collision_cut=config.self_collision_cut,
                             contact_budget=budget)
        with self.physics():        # MJX sizes the contact arrays by the contact rules (the summary's count too)
            self.sm: StackedModel = build_stacked_model(self.morphologies, self.terrain.world(), opts,
                                                        self_pair_budget=config.self_pair_budget)
        self.robots: Robots = self.sm.policy
        if config.context_features is not None:
            self.robots = self.robots._replace(context=self.robots.context * context_mask(config.context_features))
        self.tables: Tables = self.sm.tables
        self.num_robots = len(self.morphologies)
        mm = self.sm.mj_models[0]
        self._hgeom = int(np.nonzero(mm.geom_type == 1)[0][0]) if self.terrain.uses_hfield else -1  # mjGEOM_HFIELD
        self._ancestors = jnp.asarray(observation.ancestor_dofs(mm))
        # on this process's device (MJX's default, jax.devices()[0], is process 0's when there are several); inside
        # physics(): the height-field contact rule sizes the contact arrays
        with self.physics():
            self._template = jax.device_put(mjx.make_data(self.sm.model_for(0), impl="jax",
                                                          device=jax.local_devices()[0]))
        self.hfield_size = terrain.grid.HFIELD_OBS_SIZE if self.task.hfield_obs else 0

    @functools.cached_property
    def digest(self) -> str:
        """16 hex digits naming the numbers this env simulates and observes with (`model.model_digest`: the stacked
        MJX model, the robots' policy constants as the env gives them, the tables, the solver options, MuJoCo's and
        MJX's versions). Runs record it per invocation and refuse to resume onto another."""
        return model_digest(model=self.sm.model, policy=self.robots, tables=self.tables, options=self.sm.options)

    # ---- helpers ---------------------------------------------------------------------------------------------
    @contextlib.contextmanager
    def physics(self) -> Iterator[None]:
        """The block to trace this env's MJX calls in (make_data, step): its matmul precision, floor-capsule rule
        (contact.py), height-field rule (hfield_contact.py; it also sets the size of MJX's contact arrays) and
        Cholesky (linalg.py)."""
        c = self.config
        with jax.default_matmul_precision(c.matmul_precision), contact.floor(c.floor_contacts), \
                hfield_contact.rule(c.hfield_contacts, c.hfield_contacts_per_geom, c.hfield_candidates), \
                linalg.use(c.linalg):
            yield

    def _row(self, tree, robot):
        return jax.tree_util.tree_map(lambda x: x[robot], tree)

    def _model(self, robot, terrain_state, qpos):
        m = self.sm.model_for(robot)
        if self.terrain.uses_hfield:
            data, pos = self.terrain.patch(terrain_state, qpos[0], qpos[1])
            m = m.replace(hfield_data=data, geom_pos=m.geom_pos.at[self._hgeom].set(pos))
        return m

    def _obs(self, d, qpos, qvel, tab, pol, robot, terrain_state, prev_action, yaw_aligned: bool) -> Obs:
        cvel = observation.body_velocity(self._ancestors, d.cdof, qvel)     # mujoco-py's, after the step
        prop = observation.proprio(d.xpos, d.xquat, cvel, d.subtree_com, qpos, qvel, tab, pol.node_mask,
                                   pol.act_mask, self.terrain.origin)
        if self.task.hfield_obs:
            if yaw_aligned:
                yaw = jnp.float32(0.0)
            else:
                xdir = d.xmat[1, :2, 0]
                yaw = jnp.arctan2(xdir[1], xdir[0])
            hf = self.terrain.hfield_obs(terrain_state, d.xpos[1, 0], d.xpos[1, 1], yaw)
        else:
            hf = jnp.zeros((0,), jnp.float32)
        return Obs(proprio=prop.astype(jnp.float32), prev_action=prev_action, hfield=hf,
                   robot=jnp.asarray(robot, jnp.int32))

    def _observe(self, robot, qpos, qvel, ts, prev_action):
        tab, pol = self._row(self.tables, robot), self._row(self.robots, robot)
        m = self.sm.model_for(robot)
        d = self._template.replace(qpos=qpos, qvel=qvel)
        d = mjx.kinematics(m, d)
        d = mjx.com_pos(m, d)
        return self._obs(d, qpos, qvel, tab, pol, robot, ts, prev_action, yaw_aligned=True), d.xpos[1, 0]

    # ---- API ---------------------------------------------------------------------------------------------------
    @_in_physics
    def reset(self, key: jax.Array, robot: jax.Array) -> EnvState:
        robot = jnp.asarray(robot, jnp.int32)
        kq, kv, kt, knext = jax.random.split(key, 4)
        tab = self._row(self.tables, robot)
        m = self.sm.model_for(robot)
        s = self.config.reset_noise
        noise = lambda k, n: jax.random.uniform(k, (n,), jnp.float32, -s, s).astype(m.qpos0.dtype)  # noqa: E731
        qpos = m.qpos0 + noise(kq, m.qpos0.shape[0]) * tab.real_qpos       # float32 draws: under jax.enable_x64
        qvel = noise(kv, m.nv) * tab.real_dof                              # (fidelity checks) the same start
        ts = self.terrain.generate(kt)
        obs, torso_x = self._observe(robot, qpos, qvel, ts, jnp.zeros((NUM_ACTIONS,), jnp.float32))
        return EnvState(physics=Physics(qpos=qpos, qvel=qvel, qacc_warmstart=jnp.zeros_like(qvel)),
                        episode=Episode(robot=robot, t=jnp.int32(0), ret=jnp.float32(0.0), torso_x=torso_x,
                                        terrain=ts),
                        obs=obs, reward=jnp.float32(0.0), done=jnp.asarray(False), truncated=jnp.asarray(False),
                        ended=_no_stats(), key=knext)

    @_in_physics
    def observe(self, robot: jax.Array, qpos: jax.Array, qvel: jax.Array, terrain_state=None,
                prev_action: jax.Array | None = None) -> Obs:
        """The observation of an arbitrary state of robot `robot` (padded qpos/qvel layout), with kinematics
        computed from that state and an axis-aligned height map, as right after a reset."""
        robot = jnp.asarray(robot, jnp.int32)
        ts = terrain.NoTerrain() if terrain_state is None else terrain_state
        pa = jnp.zeros((NUM_ACTIONS,), jnp.float32) if prev_action is None else prev_action
        return self._observe(robot, jnp.asarray(qpos, jnp.float32), jnp.asarray(qvel, jnp.float32), ts, pa)[0]

    @_in_physics
    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        """One control step; where it ends the episode (`done`) the returned state is the terminal one (zeroed if
        unstable) and `ended` holds the episode's statistics. The key is left as it is."""
        phys, ep = state.physics, state.episode
        robot = ep.robot
        tab, pol = self._row(self.tables, robot), self._row(self.robots, robot)
        m = self._model(robot, ep.terrain, phys.qpos)
        raw = jnp.asarray(action, jnp.float32).reshape(NUM_ACTIONS)
        act = jnp.where(pol.act_mask, jnp.clip(raw, -1.0, 1.0), 0.0)
        ctrl = jnp.concatenate([act, jnp.zeros((1,), jnp.float32)])[tab.ctrl_src]
        d = self._template.replace(qpos=phys.qpos, qvel=phys.qvel, qacc_warmstart=phys.qacc_warmstart, ctrl=ctrl)
        if self.config.unroll_substeps:
            for _ in range(self.config.substeps):
                d = mjx.step(m, d)
        else:
            d = jax.lax.fori_loop(0, self.config.substeps, lambda i, dd: mjx.step(m, dd), d)

        finite = lambda x: jnp.all(jnp.isfinite(x))
        ok = (finite(d.qpos) & finite(d.qvel) & finite(d.xpos) & finite(d.xquat) & finite(d.cvel)
              & finite(d.cdof) & finite(d.subtree_com) & (jnp.max(jnp.abs(d.qvel)) <= self.config.max_qvel)
              & (jnp.max(jnp.abs(d.qpos[:3])) <= 1.0e4))
        out = reward.evaluate(self.task, self.terrain, ep.terrain, ep.torso_x, d.xpos[1], tab.orig_height, raw,
                              pol.act_mask)
        t = ep.t + 1
        rew = jnp.where(ok, out.reward, 0.0)
        fell = out.fell & ok
        oob = out.out_of_bounds & ok
        terminated = fell | oob
        timeout = (t >= self.config.episode_length) & ok & ~terminated
        unstable = ~ok
        done = terminated | timeout | unstable
        truncated = timeout | unstable
        ret = ep.ret + rew
        ended = EpisodeStats(ret=ret, length=t, robot=robot, fell=fell, out_of_bounds=oob, timeout=timeout,
                             unstable=unstable)
        # the state after the step, sanitised: nothing of an unstable state reaches the observation
        clean = lambda x: jnp.where(ok, x, 0.0)
        qpos, qvel = clean(d.qpos), clean(d.qvel)
        dd = d.replace(xpos=clean(d.xpos), xquat=clean(d.xquat), cdof=clean(d.cdof),
                       subtree_com=clean(d.subtree_com), xmat=clean(d.xmat))
        obs = self._obs(dd, qpos, qvel, tab, pol, robot, ep.terrain, act, yaw_aligned=False)
        return EnvState(physics=Physics(qpos=qpos, qvel=qvel, qacc_warmstart=clean(d.qacc_warmstart)),
                        episode=Episode(robot=robot, t=t, ret=ret, torso_x=dd.xpos[1, 0], terrain=ep.terrain),
                        obs=obs, reward=rew, done=done, truncated=truncated, ended=ended, key=state.key)


Env = AutoReset     # what `make_env` returns: a UnimalEnv with auto-reset and robot sampling (wrappers.py)


def make_env(robots: Any, task: str | Task | None = None, config: EnvConfig | None = None, **overrides) -> Env:
    """The env for a robot set name ("unimal100/train", "gen/train", a path), a RobotSet, or a list of robots:
    a `UnimalEnv` wrapped in `AutoReset`. `task` overrides `config.task` (default "ft"); other keyword arguments
    override EnvConfig fields."""
    if isinstance(robots, str):
        robots = load_set(robots).robots
    elif isinstance(robots, RobotSet):
        robots = robots.robots
    config = config or EnvConfig()
    if task is not None:
        overrides["task"] = task.name if isinstance(task, Task) else task
    config = dataclasses.replace(config, **overrides)
    return AutoReset(UnimalEnv(tuple(robots), config))
