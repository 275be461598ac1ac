"""Shared tree, padding, stacked model and robot sampling: checks that need no MJX compilation (fast)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import jax
import jax.numpy as jnp
import mujoco

from mjx_morph.sim import fidelity, model, padding, sampling, supertree
from mjx_morph.sim.model import build_stacked_model, INERT_MARGIN
from mjx_morph.sim.padding import SolverOptions
from sim_reference import available_robots
from mjx_morph.unimal.sets import load_set, unimals_root


def _robots(n: int):
    """n robots of different shapes: the shipped generated set when present, else the original train robots."""
    rs = available_robots()
    out, shapes = [], set()
    for m in rs:
        shape = supertree._robot_shape(m)
        if shape not in shapes:
            shapes.add(shape)
            out.append(m)
        if len(out) == n:
            break
    return out


def test_shared_tree_embeds_every_robot():
    rs = _robots(6)
    tree = supertree.build_shared_tree(rs)
    tree.check(rs)
    assert all(tree.parent[s] < s for s in range(1, tree.num_slots))
    assert tree.num_slots >= max(m.num_nodes for m in rs)
    assert tree.num_slots <= sum(m.num_limbs for m in rs) + 1
    assert tree.users[0] == len(rs)
    # deterministic
    assert supertree.build_shared_tree(rs) == tree


@pytest.mark.skipif(unimals_root() is None, reason="original robots not available (../shared/unimals_100)")
def test_tree_sizes_of_original_sets():
    train = supertree.build_shared_tree(load_set("unimal100/train").robots)
    test = supertree.build_shared_tree(load_set("unimal100/test").robots)
    assert train.num_slots <= 28          # 28 bodies measured when the project was designed; we find 27
    assert test.num_slots <= 29


def test_stacked_model_tables_and_masks():
    rs = _robots(3)
    sm = build_stacked_model(rs, fidelity.FLOOR_WORLD, SolverOptions())
    R, S = len(rs), sm.tree.num_slots
    mm = sm.mj_models[0]
    assert mm.nbody == S + 1 and mm.nu == 2 * (S - 1) and mm.nv == 6 + 2 * (S - 1)
    pol = jax.tree_util.tree_map(np.asarray, sm.policy)
    tab = jax.tree_util.tree_map(np.asarray, sm.tables)
    assert pol.context.shape == (R, 12, 35) and pol.node_mask.shape == (R, 12) and pol.act_mask.shape == (R, 24)
    for r, m in enumerate(rs):
        assert pol.node_mask[r].sum() == m.num_nodes and pol.node_mask[r, :m.num_nodes].all()
        assert pol.act_mask[r].sum() == m.dof
        assert not pol.act_mask[r, :2].any()                         # the torso has no joints
        for i, l in enumerate(m.limbs):
            for k, kind in enumerate("xy"):
                assert pol.act_mask[r, 2 * (i + 1) + k] == (l.joint(kind) is not None)
        # every real actuator is driven by exactly its action entry, the others by the constant zero
        driven = tab.ctrl_src[r][tab.ctrl_src[r] < 24]
        assert sorted(driven.tolist()) == np.nonzero(pol.act_mask[r])[0].tolist()
        gear = sm.mj_models[r].actuator_gear[:, 0]
        assert np.all(gear[tab.ctrl_src[r] == 24] == 0) and np.all(gear[tab.ctrl_src[r] < 24] > 0)
        # inert geoms never make contact
        margin = np.asarray(sm.model.geom_margin)[r]
        used = {0} | set(sm.tree.slot_of[r])
        for s in range(S):
            g = sm.mj_models[r].body_geomadr[s + 1]
            assert (margin[g] == INERT_MARGIN) == (s not in used)
        assert pol.context[r, m.num_nodes:].sum() == 0


def test_padded_robot_matches_robot_alone_in_mujoco_c():
    """The padding itself (locked joints, inert slots) in MuJoCo C: same masses, same motion. (With self-collision
    the inert geoms also need the stacked model's margin: `fidelity.padded_c_models`, checked by check_sim.)"""
    rs = _robots(2)
    opts = SolverOptions(iterations=100, ls_iterations=50, self_collision=False)
    tree = supertree.build_shared_tree(rs)
    # compiled as the stacked model compiles them (the solver tolerance rescaled for the locks' armature)
    padded = model.compile_padded(rs, tree, fidelity.METAMORPH_WORLD, opts)
    for r, m in enumerate(rs):
        mp = padded[r]
        ma = fidelity.alone_model(m, opts)
        bodies = [1] + [s + 1 for s in tree.slot_of[r]]
        np.testing.assert_allclose(mp.body_mass[bodies], ma.body_mass[1:], rtol=1e-12)
        np.testing.assert_allclose(mp.body_inertia[bodies], ma.body_inertia[1:], rtol=1e-12)
        t = padding.pad_tables(m, tree, r)
        order = [7 + 2 * (tree.slot_of[r][i] - 1) + "xy".index(j.kind) for i, l in enumerate(m.limbs) for j in l.joints]
        dp, da = mujoco.MjData(mp), mujoco.MjData(ma)
        rng = np.random.default_rng(r)
        for _ in range(25):
            a = rng.normal(0, 0.9, ma.nu)
            da.ctrl[:] = a
            dp.ctrl[:] = 0
            dp.ctrl[np.asarray(order) - 7] = a
            for _ in range(4):
                mujoco.mj_step(ma, da)
                mujoco.mj_step(mp, dp)
        assert np.abs(dp.xpos[bodies] - da.xpos[1:]).max() < 1e-5        # issue 12's bound on the padding's error
        pad = np.ones(mp.nq, bool)
        pad[:7] = False
        pad[order] = False
        assert np.abs(dp.qpos[pad]).max() < 1e-5                    # locked joints stay locked
        assert t.real_qpos[order].all()


def _sequential_reference(episodes, num_robots):
    """MetaMorph's meter: mean of the first 10 episodes, then EMA 0.1 per episode."""
    hist = {i: [] for i in range(num_robots)}
    ema = {i: -1.0 for i in range(num_robots)}
    for robot, length in episodes:
        hist[robot].append(length)
        n = len(hist[robot])
        if n == 10:
            ema[robot] = float(np.mean(hist[robot]))
        elif n > 10:
            ema[robot] = 0.1 * length + 0.9 * ema[robot]
    return ema, {i: len(h) for i, h in hist.items()}


def test_balanced_sampling_matches_sequential_ema():
    R = 5
    rng = np.random.default_rng(0)
    st = sampling.init(R, "balanced")
    all_eps = []
    upd = jax.jit(sampling.update)
    for it in range(35):
        T, N = 7, 6
        done = rng.random((T, N)) < 0.4
        robots = rng.integers(0, R - 1, (T, N))                   # robot R-1 never finishes an episode
        lengths = rng.integers(1, 1000, (T, N))
        all_eps += [(int(robots[t, n]), int(lengths[t, n])) for t in range(T) for n in range(N) if done[t, n]]
        st = upd(st, jnp.asarray(lengths), jnp.asarray(robots), jnp.asarray(done))
        if it < 29:
            np.testing.assert_allclose(st.probs, 1.0 / R)
    ema, count = _sequential_reference(all_eps, R)
    assert [int(c) for c in st.count] == [count[i] for i in range(R)]
    for i in range(R - 1):
        assert count[i] >= 10
        np.testing.assert_allclose(float(st.ep_len[i]), ema[i], rtol=1e-4)
    p = 1000.0 / np.array([ema[i] for i in range(R - 1)])
    p_last = p.max()                                                 # guard: no episodes -> largest probability
    want = np.append(p, p_last)
    np.testing.assert_allclose(st.probs, want / want.sum(), rtol=1e-4)
    # uniform mode never changes; draws follow the probabilities
    u = upd(sampling.init(R, "uniform"), jnp.asarray(lengths), jnp.asarray(robots), jnp.asarray(done))
    np.testing.assert_allclose(u.probs, 1.0 / R)
    keys = jax.random.split(jax.random.PRNGKey(0), 4000)
    draws = jax.vmap(lambda k: sampling.sample(k, st, R))(keys)
    freq = np.bincount(np.asarray(draws), minlength=R) / 4000
    np.testing.assert_allclose(freq, np.asarray(st.probs), atol=0.03)
    # index for index jax.random.choice's draws (the same key stream as before the loop-free lookup), and no loop
    np.testing.assert_array_equal(draws, jax.vmap(lambda k: jax.random.choice(k, R, p=st.probs))(keys))
    skewed = st._replace(probs=jnp.asarray(np.r_[0.9, np.full(R - 1, 0.1 / (R - 1))], jnp.float32))
    np.testing.assert_array_equal(jax.vmap(lambda k: sampling.sample(k, skewed, R))(keys),
                                  jax.vmap(lambda k: jax.random.choice(k, R, p=skewed.probs))(keys))
    jaxpr = str(jax.make_jaxpr(lambda k: sampling.sample(k, st, R))(keys[0]))
    assert "scan" not in jaxpr and "while" not in jaxpr          # searchsorted's default is a scan


def test_reward_and_terminations():
    from mjx_morph.sim import reward, terrain
    from mjx_morph.sim.tasks import TASKS
    orig = jnp.float32(0.8)                                     # z0 = 1.0
    act = jnp.ones(24)
    mask = jnp.zeros(24, bool).at[2].set(True)
    for name, task in TASKS.items():
        terr = terrain.for_task(task)
        ts = jax.jit(terr.generate)(jax.random.PRNGKey(0))
        ground = float(terr.ground_height(ts, jnp.float32(0.31), jnp.float32(0.0)))
        thr = 0.8 * task.stand_ratio
        x0 = 0.3
        for height, fell in [(thr + 0.01, False), (thr - 0.01, True)]:
            pos = jnp.asarray([x0 + 0.01, 0.0, ground + height], jnp.float32)
            out = reward.evaluate(task, terr, ts, jnp.float32(x0), pos, orig, act, mask)
            assert bool(out.fell) == fell, (name, height)
            speed = 0.01 / 0.02 / (np.cos(np.radians(task.incline_deg)) if task.incline_deg else 1.0)
            np.testing.assert_allclose(float(out.reward), speed, rtol=1e-3)
        side = reward.evaluate(task, terr, ts, jnp.float32(x0), jnp.asarray([x0, -19.0, ground + 1.0]), orig, act,
                               mask)
        assert bool(side.out_of_bounds) == (task.side_limit is not None)
    # incline ground: MetaMorph's array 1 + tan(10 deg) * floor(10 x) / 10
    # (at MetaMorph's x = -71.89; the env's frame is MetaMorph's world moved by -origin)
    inc = terrain.for_task(TASKS["incline"])
    ox, _, oz = inc.origin
    g = float(inc.ground_height(terrain.NoTerrain(), jnp.float32(-71.89 - ox), jnp.float32(0.0))) + oz
    np.testing.assert_allclose(g, 1 + np.tan(np.radians(10)) * np.floor(-718.9) / 10, atol=1e-3)


def _same_leaves(ref, many) -> None:
    for a, b in zip(ref, many, strict=True):
        la, ta = jax.tree_util.tree_flatten(a)
        lb, tb = jax.tree_util.tree_flatten(b)
        assert ta == tb and len(la) > 50
        for x, y in zip(la, lb):
            assert np.asarray(x).dtype == np.asarray(y).dtype and np.array_equal(x, y)


def test_env_build_spread_over_processes_gives_what_one_process_does(monkeypatch):
    """The CPU work of a large set's env build runs in several processes: compiling each padded robot and MJX's
    put_model of it (`model.compile_and_put`) and the shared tree's merge orders (`supertree.build_shared_tree`).
    Each gives what one process does, bit for bit: the same tree, the same MJX leaves (in float64 too under
    jax.enable_x64, as sim.fidelity builds its reference models) with the compiled model's signature, the same
    compiled models; and no fallback warning."""
    import warnings
    rs = _robots(3)
    serial_tree = supertree.build_shared_tree(rs, tries=4)          # 3 < PARALLEL_FROM_ROBOTS: this process
    tree = supertree.build_shared_tree(rs)
    one = {}
    for x64 in (False, True):
        with jax.enable_x64(x64):
            one[x64] = model.compile_and_put(rs, tree, fidelity.FLOOR_WORLD, SolverOptions())   # 3 < PUT_PARALLEL_FROM
    monkeypatch.setattr(model, "PUT_PARALLEL_FROM", 2)
    monkeypatch.setattr(supertree, "PARALLEL_FROM_ROBOTS", 2)
    monkeypatch.setattr(model.processes, "os", _TwoCores())
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)           # a broken pool would warn
        assert supertree.build_shared_tree(rs, tries=4) == serial_tree
    for x64 in (False, True):
        mjm, ref = one[x64]
        with jax.enable_x64(x64), warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)
            mjm2, many = model.compile_and_put(rs, tree, fidelity.FLOOR_WORLD, SolverOptions())
        _same_leaves(ref, many)
        assert np.asarray(many[0].body_mass).dtype == (np.float64 if x64 else np.float32)
        assert many[0].signature == mjm[0].signature != 0               # the compiled model's, kept by put_model
        for a, b in zip(mjm, mjm2, strict=True):                        # the compiled models, pickled back
            for f in ("body_mass", "geom_size", "jnt_range", "dof_armature", "actuator_gear", "geom_margin"):
                assert np.array_equal(getattr(a, f), getattr(b, f)), f
            assert a.opt.tolerance == b.opt.tolerance


class _TwoCores:
    """`os` with 2 usable cores, whatever this machine has (processes_for reads the affinity)."""
    def __getattr__(self, name):
        import os
        return getattr(os, name)

    @staticmethod
    def sched_getaffinity(pid):
        return {0, 1}


def test_model_digest_names_the_physics(monkeypatch):
    """The digest runs record (`UnimalEnv.digest`): the same on a rebuild, another for one float32 bit of one mass,
    for another solver cap, and for session 42's limb masses (a change of physics in the middle of a comparison that
    nothing recorded)."""
    rs = _robots(2)

    def digest(sm):
        return model.model_digest(model=sm.model, policy=sm.policy, tables=sm.tables, options=sm.options)

    sm = build_stacked_model(rs, fidelity.FLOOR_WORLD, SolverOptions())
    d = digest(sm)
    assert len(d) == 16 and int(d, 16) >= 0
    assert digest(build_stacked_model(rs, fidelity.FLOOR_WORLD, SolverOptions())) == d
    mass = np.asarray(sm.model.body_mass).copy()
    mass.flat[-1] = np.nextafter(mass.flat[-1], np.float32(np.inf), dtype=mass.dtype)
    assert digest(dataclasses.replace(sm, model=sm.model.replace(body_mass=mass))) != d
    assert digest(build_stacked_model(rs, fidelity.FLOOR_WORLD, SolverOptions(iterations=5))) != d

    # session 42's change: MetaMorph's limb masses and inertias (before it, MuJoCo's own from the capsules)
    monkeypatch.setattr(padding, "limb_inertial", lambda limb: "")
    assert digest(build_stacked_model(rs, fidelity.FLOOR_WORLD, SolverOptions())) != d
    with pytest.raises(TypeError, match=r"model_digest: x\['f'\] \(object\) has no digest"):
        model.model_digest(x={"f": object()})
