"""The batched environment on a tiny 2-robot config: reset, step, terminations, auto-reset, instability, and
observation parity with a plain NumPy implementation of the spec (tests/sim_reference.py) on MuJoCo C data.

One env and one compiled step per task (module-scoped), 3 envs, a 5-step time limit.
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import sim_reference as ref
from mjx_morph.run import FAST_COMPILE
from mjx_morph.sim import fidelity, sampling, terrain
from mjx_morph.sim.env import make_env
from mjx_morph.sim.padding import SolverOptions
from mjx_morph.sim.tasks import TASKS
from sim_reference import available_robots

EPISODE = 5
N = 3


def _two_robots():
    rs = available_robots()
    tall = [m for m in rs if m.height >= 0.7]
    a = tall[0]
    b = next(m for m in tall if m.num_limbs != a.num_limbs)
    return [a, b]


@pytest.fixture(scope="module", params=list(TASKS))
def bundle(request):
    rs = _two_robots()
    env = make_env(rs, request.param, episode_length=EPISODE)
    return env, jax.jit(env.vreset, compiler_options=FAST_COMPILE), jax.jit(env.vstep, compiler_options=FAST_COMPILE)


def _reset(bundle, robots=(0, 1, 0), seed=0):
    env, vreset, _ = bundle
    keys = jax.random.split(jax.random.PRNGKey(seed), len(robots))
    return vreset(keys, jnp.asarray(robots, jnp.int32))


def _sampler(env):
    """Uniform sampler (always pass one: a None sampler is another pytree, i.e. another compilation)."""
    return sampling.init(env.num_robots, "uniform")


def _set(st, i, **fields):
    """Copy of batched state `st` with env i's physics fields (qpos, qvel) replaced."""
    ph = st.physics
    return st._replace(physics=ph._replace(**{k: getattr(ph, k).at[i].set(v) for k, v in fields.items()}))


def test_reset(bundle):
    env, _, _ = bundle
    st = _reset(bundle)
    task = env.task
    assert st.obs.proprio.shape == (N, 12, 52) and st.obs.prev_action.shape == (N, 24)
    assert st.obs.hfield.shape == ((N, 1410) if task.hfield_obs else (N, 0))
    np.testing.assert_array_equal(st.obs.robot, [0, 1, 0])
    assert not st.done.any() and (st.episode.t == 0).all() and (st.obs.prev_action == 0).all()
    pol = jax.tree_util.tree_map(np.asarray, env.robots)
    for i, r in enumerate([0, 1, 0]):
        m = env.morphologies[r]
        prop = np.asarray(st.obs.proprio[i])
        assert np.isfinite(prop).all() and (prop[m.num_nodes:] == 0).all()
        pos, _ = env.sm.world.start_pose(m.height)
        np.testing.assert_allclose(np.asarray(st.physics.qpos[i, :3]), pos, atol=0.0051)
        # the planes are simulated with the torso starting on the ground at the origin (float32 resolves contacts
        # finely there), and observed in MetaMorph's world: the torso z = z0 + 1 on ft, z0 + 1 - 73 sin(10 deg) on
        # the incline (its start 2 m from the slab's lower end)
        if not env.terrain.uses_hfield:
            np.testing.assert_allclose(pos, (0.0, 0.0, m.height), atol=1e-12)
            a = math.radians(task.incline_deg)
            np.testing.assert_allclose(prop[0, 2], m.height + 1.0 - 73.0 * math.sin(a), atol=0.0051)
        assert pol.node_mask[r].sum() == m.num_nodes
    if task.hfield_obs:
        assert np.isfinite(np.asarray(st.obs.hfield)).all()


def test_step_time_limit_and_auto_reset(bundle):
    env, _, vstep = bundle
    st = _reset(bundle)
    act = jnp.zeros((N, 24))
    for t in range(1, EPISODE + 1):
        prev = st
        st = vstep(st, act, _sampler(env))
        assert np.isfinite(np.asarray(st.reward)).all()
        assert np.isfinite(np.asarray(st.obs.proprio)).all()
        if t < EPISODE:
            assert not st.done.any(), f"an episode ended at step {t} standing still"
            np.testing.assert_array_equal(st.episode.t, t)
            # reward = forward speed of the torso
            dx = np.asarray(st.episode.torso_x - prev.episode.torso_x) / 0.02
            if env.task.incline_deg:
                dx = dx / math.cos(math.radians(env.task.incline_deg))
            np.testing.assert_allclose(st.reward, dx, rtol=1e-4, atol=1e-4)
    assert st.done.all() and st.truncated.all() and st.ended.timeout.all()
    assert not st.ended.fell.any() and not st.ended.unstable.any()
    np.testing.assert_array_equal(st.ended.length, EPISODE)
    np.testing.assert_array_equal(st.episode.t, 0)                 # auto-reset: a new episode started
    assert (st.obs.prev_action == 0).all() and (st.episode.ret == 0).all()


def test_actions_are_masked_and_clamped(bundle):
    env, _, vstep = bundle
    st = _reset(bundle)
    act = jnp.full((N, 24), 3.0, jnp.float32)
    st = vstep(st, act, _sampler(env))
    am = np.asarray(env.robots.act_mask)[[0, 1, 0]]
    np.testing.assert_array_equal(np.asarray(st.obs.prev_action), np.where(am, 1.0, 0.0))


def test_fall_terminates(bundle):
    env, _, vstep = bundle
    task = env.task
    if isinstance(env.terrain, terrain.InclinedPlane):
        pytest.skip("incline fall threshold is below the torso radius for these robots "
                    "(tests/test_sim_tree.py::test_reward_and_terminations)")
    st = _reset(bundle)
    q = np.asarray(st.physics.qpos[0]).copy()
    q[2] = 1.0 - env.terrain.origin[2] + 0.105           # torso resting on the floor (z = 1 in MetaMorph's world)
    q[3:7] = [0.0, 1.0, 0.0, 0.0]
    st = _set(st, 0, qpos=jnp.asarray(q), qvel=jnp.zeros_like(st.physics.qvel[0]))
    st = vstep(st, jnp.zeros((N, 24)), _sampler(env))
    assert bool(st.done[0]) and bool(st.ended.fell[0])
    assert not bool(st.truncated[0]) and not bool(st.ended.unstable[0])
    assert not st.done[1:].any()
    assert int(st.episode.t[0]) == 0 and int(st.ended.length[0]) == 1


def test_side_limit_terminates(bundle):
    env, _, vstep = bundle
    if env.task.side_limit is None:
        pytest.skip("ft has no side limit")
    st = _reset(bundle)
    q = np.asarray(st.physics.qpos[1]).copy()
    q[1] = 19.2
    st = _set(st, 1, qpos=jnp.asarray(q))
    st = vstep(st, jnp.zeros((N, 24)), _sampler(env))
    assert bool(st.done[1]) and bool(st.ended.out_of_bounds[1]) and not bool(st.truncated[1])


def test_instability_resets_and_is_counted(bundle):
    env, _, vstep = bundle
    st = _reset(bundle)
    v = np.asarray(st.physics.qvel[0]).copy()
    v[0] = np.nan
    st = _set(st, 0, qvel=jnp.asarray(v))
    v2 = np.asarray(st.physics.qvel[2]).copy()
    v2[6:] = 1e5 * np.asarray(env.tables.real_dof[0, 6:])              # exploding joint velocities
    st = _set(st, 2, qvel=jnp.asarray(v2))
    st = vstep(st, jnp.zeros((N, 24)), _sampler(env))
    for i in (0, 2):
        assert bool(st.done[i]) and bool(st.ended.unstable[i]) and bool(st.truncated[i])
        assert not bool(st.ended.fell[i]) and float(st.reward[i]) == 0.0
        assert int(st.episode.t[i]) == 0
    assert not bool(st.done[1])
    for leaf in jax.tree_util.tree_leaves(st.obs):
        assert np.isfinite(np.asarray(leaf, np.float64)).all()
    assert np.isfinite(np.asarray(st.physics.qpos)).all() and np.isfinite(np.asarray(st.physics.qvel)).all()


def test_auto_reset_draws_from_sampler(bundle):
    env, _, vstep = bundle
    st = _reset(bundle, robots=(0, 0, 0))
    sampler = sampling.init(env.num_robots)._replace(probs=jnp.asarray([0.0, 1.0]))
    v = np.asarray(st.physics.qvel[1]).copy()
    v[0] = np.inf
    st = _set(st, 1, qvel=jnp.asarray(v))
    st = vstep(st, jnp.zeros((N, 24)), sampler)
    assert bool(st.done[1]) and int(st.episode.robot[1]) == 1 and int(st.obs.robot[1]) == 1
    assert int(st.ended.robot[1]) == 0
    np.testing.assert_array_equal(np.asarray(st.episode.robot)[[0, 2]], 0)


# ---- observation parity with the NumPy reference on MuJoCo C data --------------------------------------------------
def test_proprio_and_context_match_numpy_reference(bundle):
    env, _, _ = bundle
    if env.task.name != "ft":
        pytest.skip("checked on ft (the robot features do not depend on the task)")
    observe = jax.jit(env.observe)
    pol = jax.tree_util.tree_map(np.asarray, env.robots)
    rng = np.random.default_rng(0)
    for r, m in enumerate(env.morphologies):
        ma = fidelity.alone_model(m, SolverOptions())
        ent = np.nonzero(pol.act_mask[r])[0]
        for trial in range(3):
            # a random state: torso anywhere and rotated, joints inside their ranges, random velocities
            q = ma.qpos0.copy()
            q[:3] = [rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(1.2, 2.0)]
            quat = rng.normal(size=4)
            q[3:7] = quat / np.linalg.norm(quat)
            lo, hi = ma.jnt_range[1:, 0], ma.jnt_range[1:, 1]
            q[7:] = rng.uniform(lo, hi)
            v = rng.normal(0, 2.0, ma.nv)
            d = mujoco.MjData(ma)
            d.qpos[:], d.qvel[:] = q, v
            mujoco.mj_forward(ma, d)
            want = ref.proprio(ma, d, env.terrain.origin)
            qp, vp = fidelity.to_padded(env.sm, r, q, v)
            got = np.asarray(observe(r, qp, vp).proprio)
            np.testing.assert_allclose(got, want, rtol=1e-5, atol=2e-5, err_msg=f"{m.name} trial {trial}")
        np.testing.assert_allclose(pol.context[r], ref.context(ma), rtol=1e-5, atol=1e-5)
        # ModuMorph's fixed bounds were set on its robots, so a context far outside [-1, 1] is a compile defect
        # (sessions 42-43's off-axis inertial frame gave 5e7 on these robots; generated limbs reach -1.008)
        assert np.abs(pol.context[r]).max() <= 1.1, m.name
        node, act = ref.masks(ma)
        np.testing.assert_array_equal(pol.node_mask[r], node)
        np.testing.assert_array_equal(pol.act_mask[r], act)


def test_observation_after_a_step_matches_mujoco_py_after_mj_step(bundle):
    """After a control step the observed body velocities are mujoco-py's `body_xvelp/xvelr` read after `mj_step`
    (the Jacobian of the last substep's start times the new qvel), checked against MuJoCo C on the same start state
    and actions. In free fall the velocity changes by g * dt = 0.05 m/s per substep, so one substep's staleness
    (MuJoCo's `cvel`) would fail this by far."""
    env, vreset, vstep = bundle
    if env.task.name != "ft":
        pytest.skip("checked on ft")
    pol = jax.tree_util.tree_map(np.asarray, env.robots)
    rng = np.random.default_rng(1)
    st = _reset(bundle, robots=(0, 1, 0))
    wants, actions = [], np.zeros((N, 24))
    for r, m in enumerate(env.morphologies):
        ma = fidelity.alone_model(m, SolverOptions())
        ent = np.nonzero(pol.act_mask[r])[0]
        q = ma.qpos0.copy()
        q[2] += 2.0                                             # in the air: no contact in one control step
        q[7:] = rng.uniform(ma.jnt_range[1:, 0], ma.jnt_range[1:, 1]) * 0.5
        v = rng.normal(0, 1.0, ma.nv)
        a = rng.uniform(-1, 1, len(ent))
        d = mujoco.MjData(ma)
        d.qpos[:], d.qvel[:], d.ctrl[:] = q, v, a
        for _ in range(4):
            mujoco.mj_step(ma, d)
        wants.append(ref.proprio(ma, d, env.terrain.origin))
        qp, vp = fidelity.to_padded(env.sm, r, q, v)
        actions[r, ent] = a
        st = _set(st, r, qpos=jnp.asarray(qp, jnp.float32), qvel=jnp.asarray(vp, jnp.float32))
    st = vstep(st, jnp.asarray(actions, jnp.float32), _sampler(env))
    for r in range(2):
        got = np.asarray(st.obs.proprio[r])
        want = wants[r]
        np.testing.assert_allclose(got[:, 3:9], want[:, 3:9], atol=2e-4, err_msg="body velocities")
        np.testing.assert_allclose(got[:, :3], want[:, :3], atol=2e-4, err_msg="body positions")


def test_hfield_obs_and_torso_height_match_numpy_reference(bundle):
    env, _, _ = bundle
    task = env.task
    if not task.hfield_obs:
        pytest.skip("no height map in this task")
    st = _reset(bundle, seed=3)
    ts = jax.tree_util.tree_map(lambda x: np.asarray(x[0]), st.episode.terrain)
    walls = isinstance(env.terrain, terrain.ObstacleField)
    H = (ref.obstacle_H(ts.col, ts.row, ts.sx, ts.sy, ts.valid) if walls else
         ref.corridor_H(ts.seg_end, ts.seg_kind, ts.seg_height, ts.seg_rug, ts.band_end, ts.band_f, ts.band_clip))
    # the reset observation (axis-aligned) at the torso position
    x, y = float(st.physics.qpos[0, 0]), float(st.physics.qpos[0, 1])
    np.testing.assert_allclose(np.asarray(st.obs.hfield[0]), ref.hfield_obs(H, walls, x, y, None), atol=2e-6)
    # rotated grids anywhere in the world (pure terrain function)
    obs_fn = jax.jit(env.terrain.hfield_obs)
    tsj = jax.tree_util.tree_map(lambda x: x[0], st.episode.terrain)
    rng = np.random.default_rng(1)
    for _ in range(20):
        x, y, a = rng.uniform(-2, 100), rng.uniform(-19, 19), rng.uniform(-np.pi, np.pi)
        want = ref.hfield_obs(H, walls, x, y, np.array([np.cos(a), np.sin(a)]))
        got = np.asarray(obs_fn(tsj, jnp.float32(x), jnp.float32(y), jnp.float32(a)))
        assert np.abs(got - want).max() < 2e-6, (x, y, a)
        r, c = ref.torso_idx(H, walls, x, y)
        ground = float(env.terrain.ground_height(tsj, jnp.float32(x), jnp.float32(y)))
        assert abs(ground - max(0.0, H[r, c])) < 1e-6


def test_robot_stands_on_raised_terrain(bundle):
    """The per-env height-field patch is where MJX collides: a robot dropped 1 cm onto the 0.6 m plateau of a
    csr steps segment moves exactly as the same robot dropped onto the flat start (without ground under it, it
    would fall 3 cm further in these 0.08 s)."""
    env, _, vstep = bundle
    if not isinstance(env.terrain, terrain.CorridorField):
        pytest.skip("checked on csr (obstacle uses the same patch code; tests/test_sim_fidelity.py ray-casts both)")
    for seed in range(40):
        st = _reset(bundle, seed=seed)
        ts = jax.tree_util.tree_map(lambda x: np.asarray(x[0]), st.episode.terrain)
        starts = np.r_[0, ts.seg_end[:-1]]
        steps = [k for k in range(len(ts.seg_end))
                 if ts.seg_kind[k] == terrain.corridor.STEPS and ts.seg_end[k] > starts[k]]
        if steps:
            break
    else:
        pytest.skip("no steps segment in 40 corridors")
    k = steps[0]
    c = int((starts[k] + ts.seg_end[k]) // 2)
    top = float(env.terrain.physical_height(jax.tree_util.tree_map(lambda x: x[0], st.episode.terrain),
                                            jnp.int32(c), jnp.int32(200)))
    assert abs(top - 1.6) < 1e-5
    flat = np.asarray(st.physics.qpos[0]).copy()
    flat[2] -= 0.19                     # robots start with their lowest point ~0.2 m above the ground
    plateau = flat.copy()
    plateau[0], plateau[1], plateau[2] = -3 + c / 10 + 0.05, 0.0, flat[2] + 0.6
    zero = jnp.zeros_like(st.physics.qvel[0])
    st = _set(_set(st, 0, qpos=jnp.asarray(plateau), qvel=zero), 2, qpos=jnp.asarray(flat), qvel=zero)
    for _ in range(EPISODE - 1):
        st = vstep(st, jnp.zeros((N, 24)), _sampler(env))
    assert not bool(st.done[0]) and not bool(st.done[2])
    dz_plateau = float(st.physics.qpos[0, 2]) - plateau[2]
    dz_flat = float(st.physics.qpos[2, 2]) - flat[2]
    assert abs(dz_plateau - dz_flat) < 5e-3, (dz_plateau, dz_flat)


def test_a_limb_framed_off_its_axis_is_refused(monkeypatch):
    """A limb whose inertial frame is not its capsule's (a `fullinertia` lets MuJoCo pick one in the plane of the
    two equal moments) would put a z component where ModuMorph's context bounds are both 0: a context of ~1e8 (as
    session 44's R-MeMo run got). The env refuses it, naming the robot and the token."""
    from mjx_morph.sim import padding
    from mjx_morph.unimal.mjcf import format_vector

    def full_inertia(l):
        across, _, axial = l.principal_inertia()
        axis = np.asarray(l.tip, np.float64) / l.length
        i = across * np.eye(3) + (axial - across) * np.outer(axis, axis)
        full = (i[0, 0], i[1, 1], i[2, 2], i[0, 1], i[0, 2], i[1, 2])
        return (f'<inertial pos="{format_vector(np.asarray(l.tip, np.float64) / 2)}" mass="{float(l.mass)!r}" '
                f'fullinertia="{format_vector(full)}"/>')

    robots = _two_robots()
    make_env(robots)                                            # the capsule's own frame: accepted
    monkeypatch.setattr(padding, "limb_inertial", full_inertia)
    with pytest.raises(ValueError, match=r"robot \S+, token \d+: body_iquat / geom_quat has a z component"):
        make_env(robots)


@pytest.mark.parametrize("arch", ["metamorph", "rmemo", "modumorph", "rmomo"])
def test_every_model_starts_in_scale_on_the_shipped_robots(bundle, arch):
    """The four paper models, at initialisation on the env's first observations (normalised as the trainer does),
    give values and mean actions of order one: an input out of scale shows here on the CPU before any GPU time
    (sessions 42-43's contexts of ~1e8 gave R-MeMo values of 1e4-1e6; `run.loop.HealthWarnings` stops such a run)."""
    from mjx_morph.ppo.stats import RunningMeanStd
    from mjx_morph.ppo.trainer import normalize_obs
    env = bundle[0]
    if env.task.name != "ft":
        pytest.skip("checked on ft (the inputs at issue do not depend on the task)")
    obs = _reset(bundle).obs
    flat = obs.proprio.reshape(obs.proprio.shape[0], -1)
    obs = normalize_obs(RunningMeanStd.create((flat.shape[1],)).update(flat), obs)
    from mjx_morph.run import compose_run_config, make_model_for
    model = make_model_for(compose_run_config([f"arch={arch}"]))    # with the run's defaults (R-MeMo's context MLP)
    params = model.init(jax.random.PRNGKey(0), env.robots, jax.tree.map(lambda x: x[:1], obs))
    step = jax.jit(lambda p, o, c, f: model.step(p, env.robots, o, c, f), compiler_options=FAST_COMPILE)
    mu, value, _ = step(params, obs, model.initial_carry(N), jnp.ones((N,), bool))
    assert float(jnp.abs(value).max()) < 10.0 and float(jnp.abs(mu).max()) < 10.0, (arch, value, mu)
