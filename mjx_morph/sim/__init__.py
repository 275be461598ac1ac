"""mjx_morph.sim: many UNIMAL robots in one batched MuJoCo-MJX simulation.

Data flow (one idea per module):
    supertree    shared tree of a robot set, the embedding of every robot, topology groups
    selfcontact  which slot pairs of a set can ever touch (the self-collision pair cut; a provable bound)
    padding      MJCF of a robot padded onto the tree (locked joints, inert slots, excluded self pairs) + its
                 index tables
    model        compile, fix up and stack the padded robots into one mjx.Model with a robot axis;
                 per-robot constants for the policy (`Robots`) and the simulation (`Tables`)
    tasks        the four tasks' constants (ft, incline, csr, obstacle)
    terrain      one object per kind of ground (plane, inclined plane, csr corridor, obstacle field), chosen from
                 the task: its world MJCF, per-episode random terrain, ground height, and for csr / obstacle
                 MetaMorph's height array, the moving height-field patch and the 1410-value height-map observation
                 (terrain/grid.py, terrain/corridor.py, terrain/obstacles.py)
    observation  the 12 x 52 proprioceptive observation
    reward       reward, fall and side-limit terminations
    sampling     balanced / uniform robot sampling (a state the training loop updates once per iteration)
    env          `UnimalEnv`: the task (reset / step without reset / observe); `make_env`
    wrappers     `AutoReset`: auto-reset into a sampled robot, batched vreset / vstep / init (what make_env returns)
    contact      floor-capsule contacts for MJX as MuJoCo C makes them against MetaMorph's box floor; unused slots'
                 contacts ranked last for a contact budget (`never_ranked`)
    hfield_contact  height-field sphere / capsule contacts for MJX as MuJoCo C makes them (one per prism)
    linalg       which Cholesky factor / solve MJX uses (`EnvConfig.linalg`: jax | pallas), given to MJX's modules
                 while an env's step is traced
    cpu_linalg   pure-JAX Cholesky for MJX on CPU with jaxlib < 0.11 (deadlock workaround; linalg's "jax" there)
    gpu_linalg   one fused Pallas kernel per Cholesky factorisation and per solve (linalg's "pallas"; Triton on GPU)
    fidelity     padded MJX robots against the robots alone in MuJoCo C (`experiments.check_sim`)

Public API:
    env = make_env(robots, task=None, config=None, **EnvConfig overrides)   # robots: set name, RobotSet, list
    env.robots: Robots(context (R,12,35), node_mask (R,12) True = real, act_mask (R,24) True = real)
    env.reset(key, robot) -> EnvState;  env.step(state, action (24,), sampler=None) -> EnvState
    env.vreset(keys, robots);  env.vstep(states, actions (N,24), sampler);  env.init(key, num_envs, sampler)
    env.observe(robot, qpos, qvel, terrain_state=None, prev_action=None) -> Obs
    env.terrain: the task's terrain object;  env.env: the UnimalEnv inside the wrapper
    EnvState.physics: Physics(qpos, qvel, qacc_warmstart);  EnvState.episode: Episode(robot, t, ret, torso_x,
        terrain) (the running episode);  EnvState.obs: Obs(proprio (12,52) raw, prev_action (24,), hfield (1410,)
        or (0,), robot ())
    EnvState.reward / done / truncated / ended (EpisodeStats of the episode that ended at this step: ret, length,
        robot, fell, out_of_bounds, timeout, unstable; meaningful where done)
    sampling.init(R, "balanced" | "uniform"); sampling.update(state, lengths, robots, done); state.probs

Process-wide patches of MJX, made once when this package is imported (below): `contact.install()` (the
floor-capsule collider of every MJX step traced in the process applies the rule of the `contact.floor(rule)` block
being traced, MuJoCo C's box-face contacts outside any; an env traces its step inside `floor(config.floor_contacts)`;
limb-limb and torso-limb contacts are MuJoCo C's closed forms instead of MJX's regularised ones),
`hfield_contact.install()` (likewise the height-field sphere / capsule colliders and `hfield_contact.rule(...)`,
MuJoCo C's contacts outside any block; the rule also sizes MJX's contact arrays, so an env runs `make_data` and its
steps inside `UnimalEnv.physics()`) and `linalg.install()` (MJX's Cholesky factor / solve: those of the
`linalg.use(name)` block being traced, JAX's own outside any, pure-JAX loops instead on CPU with jaxlib < 0.11; an
env traces inside `use(config.linalg)`).

Deviations from MetaMorph / ModuMorph (each documented in its module):
- solver: at most 16 Newton iterations and 8 line-search iterations instead of 100 / 50, the same converged solve
  (env.py; until session 43 5 / 8, unconverged; fidelity numbers in docs/benchmarks.md); physics in float32;
- ft / incline floors are infinite planes through the top face of MetaMorph's floor boxes, whose capsule contacts
  are those MuJoCo C makes against the boxes (contact.py; the boxes' edges are not modelled: ft's box is 200 m wide,
  incline's slab 40 m wide and 150 m long); csr / obstacle use one moving 0.1 m height-field patch
  built from MetaMorph's height array, so observation and physics agree: no rugged-square y-mirror
  (terrain/corridor.py), obstacles are columns standing on the floor instead of boxes floating 0.1 m above it
  (terrain/obstacles.py); their terrain contacts are MuJoCo C's height-field contacts (hfield_contact.py), at
  most 32 per geom and, with the robot's own, at most 64 per env, the deepest (`EnvConfig.contact_budget`);
- ft and incline are simulated in MetaMorph's world moved so that the torso starts on the ground at the origin
  (`Terrain.origin`: ft 1 m down, incline 72 m along x and 11.7 m up), where float32 resolves the contacts finely;
  the observation adds the origin back (observation.py), so the policy sees MetaMorph's coordinates (terrain/);
- a NaN or exploding state ends the episode as `unstable` (MetaMorph: a MuJoCo exception silently skipped the
  remaining substeps) (env.py);
- body_xvelp / body_xvelr are mujoco-py's read after `mj_step` (velocity of the body origin, the new qvel), as
  MetaMorph read them (observation.py).
"""
# MJX is patched once, when this package is imported (the missing-Warp message was silenced by mjx_morph's
# own import): MuJoCo C's floor-capsule and robot-robot contacts (contact.py), MuJoCo C's height-field contacts
# (hfield_contact.py) and the env's choice of Cholesky (linalg.py; on old CPU jaxlibs a pure-JAX one by default).
from . import contact, hfield_contact, linalg  # noqa: E402

contact.install()
hfield_contact.install()
linalg.install()
