"""The self-collision pair cut (mjx_morph/sim/selfcontact.py): kinematics, soundness against dense samples, the
padded models' MJX pairs, and a hand-made robot with one obviously touching and one obviously far pair."""
from __future__ import annotations

import dataclasses
import json
import warnings

import mujoco
import numpy as np
import pytest
from mujoco.mjx._src import collision_driver

from mjx_morph.run import FAST_COMPILE
from mjx_morph.sim import fidelity, padding, processes, selfcontact
from mjx_morph.sim.model import build_stacked_model, compile_padded, self_pair_summary
from mjx_morph.sim.padding import SolverOptions
from mjx_morph.sim.supertree import build_shared_tree
from mjx_morph.unimal.mjcf import compile_model
from mjx_morph.unimal.morphology import TORSO, Joint, Limb, Morphology


@pytest.fixture(scope="module")
def robots(unimals):
    """4 robots of unimal100/train of different sizes (the fixture skips when the original robots are absent)."""
    from mjx_morph.unimal.sets import load_set
    rs = load_set("unimal100/train").robots
    return [rs[i] for i in (0, 1, 4, 9)]


def test_segment_distance_matches_a_dense_grid():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(300, 4, 3))
    p[:60, 1] = p[:60, 0]                                   # point vs segment
    p[60:100, 3] = p[60:100, 2]                             # segment vs point
    p[100:130, 2:] = p[100:130, :2] + 0.3                   # parallel
    p[130:150, 3] = p[130:150, 2] + 2 * (p[130:150, 1] - p[130:150, 0])
    d = selfcontact.segment_distance(p[:, 0], p[:, 1], p[:, 2], p[:, 3])
    s = np.linspace(0.0, 1.0, 201)
    a = p[:, 0, None] + s[None, :, None] * (p[:, 1] - p[:, 0])[:, None]
    b = p[:, 2, None] + s[None, :, None] * (p[:, 3] - p[:, 2])[:, None]
    grid = np.linalg.norm(a[:, :, None] - b[:, None, :], axis=-1).min(axis=(1, 2))
    assert np.all(d <= grid + 1e-12)                        # a true distance: never above a sampled one
    assert np.all(grid - d < 2e-2)                          # ... and close to it (grid step 1/200)


def test_forward_kinematics_matches_mujoco(robots):
    rng = np.random.default_rng(1)
    for m in robots:
        mm = compile_model(m)
        kin = selfcontact.kinematics(mm)
        q = kin.joint_lo - 0.3 + rng.random((40, kin.num_joints)) * (kin.joint_hi - kin.joint_lo + 0.6)
        poses = selfcontact.forward_kinematics(kin, q)
        seg = selfcontact.segments(kin, poses)
        d = mujoco.MjData(mm)
        for i in range(len(q)):
            d.qpos[:] = 0.0
            d.qpos[3] = 1.0                                  # torso at the origin, unrotated
            d.qpos[7:] = q[i]
            mujoco.mj_kinematics(mm, d)
            np.testing.assert_allclose(poses.pos[i], d.xpos[1:], atol=1e-12)
            np.testing.assert_allclose(poses.rot[i], d.xmat[1:].reshape(-1, 3, 3), atol=1e-12)
            np.testing.assert_allclose(poses.anchor[i], d.xanchor[1:], atol=1e-12)
            np.testing.assert_allclose(poses.axis[i], d.xaxis[1:], atol=1e-12)
            np.testing.assert_allclose(seg[i].mean(axis=1), d.geom_xpos, atol=1e-12)


def test_cut_keeps_every_pair_that_touches_in_a_dense_sample(robots):
    for m in robots:
        found = selfcontact.robot_pairs(m)
        assert found.kept <= set(found.candidates) and not (found.touching & found.unresolved)
        for slack in (0.0, selfcontact.SLACK):           # the joint ranges, and widened as the cut assumes
            touched = selfcontact.sampled_touching_pairs(m, samples=3000, slack=slack, seed=2)
            assert touched <= found.kept, (m.name, slack, sorted(touched - found.kept))


def test_pairs_proved_apart_stay_apart_under_descent(robots):
    """An adversarial check of the bounds: gradient descent from many random poses (half of the joints at a limit)
    never brings a pair the cut dropped within the margin."""
    rng = np.random.default_rng(3)
    for m in robots[:2]:
        kin = selfcontact.kinematics(compile_model(m))
        found = selfcontact.robot_pairs(m)
        apart = [p for p in found.candidates if p not in found.kept]
        assert apart, m.name
        pid = np.repeat(np.arange(len(apart)), 48)
        pa = np.array([p[0] for p in apart])[pid]
        pb = np.array([p[1] for p in apart])[pid]
        masks = [selfcontact.moving_joints(kin, a, b) for a, b in apart]
        on_a = np.stack([x[0] for x in masks])[pid]
        on_b = np.stack([x[1] for x in masks])[pid]
        lo = np.broadcast_to(kin.joint_lo - selfcontact.SLACK, on_a.shape)
        hi = np.broadcast_to(kin.joint_hi + selfcontact.SLACK, on_a.shape)
        u = rng.random(on_a.shape)
        u = np.where(rng.random(on_a.shape) < 0.5, np.round(u), u)
        best = selfcontact.descend(kin, lo + u * (hi - lo), lo, hi, pa, pb, on_a, on_b, steps=60)
        assert best.min() > selfcontact.MARGIN, m.name


def _geom_pairs(mm):
    return {(int(a), int(b)) for a, b, _ in collision_driver.geom_pairs(mm)}


def test_padded_models_check_exactly_the_kept_pairs(robots):
    rs = robots[:3]
    tree = build_shared_tree(rs)
    world = fidelity.FLOOR_WORLD
    sm = build_stacked_model(rs, world, SolverOptions(self_collision=True))
    kept = sm.options.self_pairs
    assert kept == selfcontact.touching_slot_pairs(rs, sm.tree)
    assert kept <= selfcontact.used_slot_pairs(rs, sm.tree) <= selfcontact.candidate_slot_pairs(sm.tree)
    for mm in sm.mj_models:
        floor = [g for g in range(mm.ngeom) if mm.geom_bodyid[g] == 0]
        geom = lambda s: int(mm.body_geomadr[s + 1])
        want = {tuple(sorted((geom(s), geom(t)))) for s, t in kept}
        want |= {tuple(sorted((f, int(mm.body_geomadr[b])))) for f in floor for b in range(1, mm.nbody)}
        assert _geom_pairs(mm) == want
    summary = sm.self_contact
    assert summary.cut and summary.kept == len(kept) and summary.candidates == len(
        selfcontact.candidate_slot_pairs(sm.tree))
    assert summary.touching is not None and summary.touching <= summary.kept
    assert dict(summary.mjx_pairs)["capsule-capsule"] + dict(summary.mjx_pairs).get("sphere-capsule", 0) == len(kept)
    assert f"kept {len(kept)} of {summary.candidates} candidates ({summary.used} used by some robot" in summary.line()
    alone = self_pair_summary(rs, world, SolverOptions(self_collision=True))   # without the MJX model: the same
    assert dataclasses.replace(alone, seconds=0.0) == dataclasses.replace(summary, seconds=0.0)
    # without the cut: every pair that is not parent-child
    no_cut = SolverOptions(self_collision=True, self_collision_cut=False)
    mm = compile_padded(rs, tree, world, no_cut)[0]
    S = tree.num_slots
    assert len(_geom_pairs(mm)) == len(selfcontact.candidate_slot_pairs(tree)) + S
    summary = self_pair_summary(rs, world, no_cut)
    assert not summary.cut and summary.kept == summary.candidates and "no cut" in summary.line()
    assert padding.excluded_slot_pairs(tree, no_cut) == []
    # self-collision off: robot-floor pairs only, and no excludes written
    off = SolverOptions(self_collision=False)
    assert "<exclude" not in padding.padded_mjcf(rs[0], tree, 0, world, off)
    assert len(_geom_pairs(compile_padded(rs[:1], build_shared_tree(rs[:1]), world, off)[0])) == rs[0].num_nodes


def _limb(i, pos, tip, lo=-10.0, hi=10.0, parent=TORSO):
    return Limb(id=i, parent=parent, pos=pos, tip=tip,
                joints=(Joint(kind="y", pos=(0.0, 0.0, 0.0), axis=(0.0, 1.0, 0.0), range=(lo, hi), gear=100.0),))


def test_hand_made_robot_keeps_the_touching_pair_and_cuts_the_far_one():
    """Limbs 0 and 1 leave the torso 20 degrees apart, so their capsules overlap at the torso; limbs 2 and 3 point
    away from each other on opposite sides and turn by only 10 degrees; limb 4 hangs from limb 2."""
    c, s = np.cos(np.radians(20.0)), np.sin(np.radians(20.0))
    limbs = (
        _limb(0, (0.0, 0.1, 0.0), (0.0, 0.2, 0.0)),
        _limb(1, (0.0, 0.1 * c, 0.1 * s), (0.0, 0.2 * c, 0.2 * s)),
        _limb(2, (0.1, 0.0, 0.0), (0.3, 0.0, 0.0)),
        _limb(3, (-0.1, 0.0, 0.0), (-0.3, 0.0, 0.0)),
        _limb(4, (0.3, 0.0, 0.0), (0.0, 0.0, -0.3), parent=2),
    )
    m = Morphology(name="hand-made", height=0.5, limbs=limbs)
    found = selfcontact.robot_pairs(m)
    node = lambda limb_index: limb_index + 1
    assert (node(0), node(1)) in found.touching
    assert (node(2), node(3)) not in found.kept
    assert (node(3), node(4)) not in found.kept            # far side, across the torso
    assert (0, node(4)) not in found.kept                  # the torso and limb 2's child, 0.2 m beyond the torso
    assert not found.unresolved
    tree = build_shared_tree([m])
    kept = selfcontact.touching_slot_pairs([m], tree)
    assert selfcontact.slot_pair(tree, 0, node(0), node(1)) in kept
    assert selfcontact.slot_pair(tree, 0, node(2), node(3)) not in kept
    # a second robot with limb 2's joint range opened to 170 degrees brings limb 4 round to limb 3
    wide = dataclasses.replace(m, limbs=limbs[:2] + (_limb(2, (0.1, 0.0, 0.0), (0.3, 0.0, 0.0), -170, 170),)
                               + limbs[3:])
    assert (node(3), node(4)) in selfcontact.robot_pairs(wide).touching


def test_limb_pair_budget_loses_no_pair(robots):
    """With the budget (MJX's closest-pairs cull at the most limb pairs any robot has, inert geoms out of the broad
    phase) the stacked MJX model moves exactly as without it: same body positions over 15 control steps of random
    actions, for robots whose limbs touch each other."""
    import jax
    import jax.numpy as jnp
    from mujoco import mjx
    from mjx_morph.sim.model import limb_pair_budget

    world = fidelity.FLOOR_WORLD
    tree = build_shared_tree(robots)
    with_budget = build_stacked_model(robots, world, SolverOptions(), tree=tree)
    without = build_stacked_model(robots, world, SolverOptions(), tree=tree, self_pair_budget=False)
    budget = with_budget.options.self_pair_budget
    limb_pairs = sum(1 for s, t in with_budget.options.self_pairs if s > 0)
    assert budget == limb_pair_budget(tree, with_budget.options) and budget < limb_pairs     # it does cull
    assert without.options.self_pair_budget is None
    assert with_budget.self_contact.mjx_contacts < without.self_contact.mjx_contacts
    rng = np.random.default_rng(0)
    nu = with_budget.mj_models[0].nu
    ctrls = jnp.asarray(rng.uniform(-1, 1, (len(robots), 15, nu)), jnp.float32)

    def rollout(sm):
        template = mjx.make_data(sm.model_for(0), impl="jax")

        def run(robot, ctrl):
            m = sm.model_for(robot)
            d = template.replace(qpos=m.qpos0)

            def control(d, c):
                d = jax.lax.fori_loop(0, 4, lambda i, dd: mjx.step(m, dd), d.replace(ctrl=c))
                con = d._impl.contact
                active = con.dist < con.includemargin
                limbs = jnp.all(jnp.asarray(m.geom_type)[con.geom] == 3, axis=1)   # capsule-capsule
                return d, (d.xpos, jnp.sum(active), jnp.sum(active & limbs))
            return jax.lax.scan(control, d, ctrl)[1]
        return jax.jit(jax.vmap(run), compiler_options=FAST_COMPILE)(jnp.arange(len(robots)), ctrls)

    (xa, na, la), (xb, nb, lb) = rollout(with_budget), rollout(without)
    np.testing.assert_allclose(np.asarray(xa), np.asarray(xb), atol=1e-5)
    # contacts with the floor and between limbs happened, the same number with and without the budget
    np.testing.assert_array_equal(np.asarray(na), np.asarray(nb))
    np.testing.assert_array_equal(np.asarray(la), np.asarray(lb))
    assert np.asarray(la).sum() > 0


def test_search_is_shared_by_geometry_and_spread_over_processes(robots):
    """Variants that change dynamics only share their base robot's search (the cache key is the geometry); kinematic
    variants do not; a search spread over processes gives what one process finds."""
    from mjx_morph.unimal.variants import CHANGE_TYPES, DYNAMICS_TYPES, robot_variants
    base = robots[0]
    digest = selfcontact.geometry_digest
    for change in CHANGE_TYPES:
        v = robot_variants(base, change, per_type=1)[0]
        assert (digest(v) == digest(base)) == (change in DYNAMICS_TYPES), change
    margin = 0.0123                                        # settings no other test uses: nothing cached
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)       # the pool's fallback to one process would warn
        found = selfcontact.robots_pairs(robots[:3], margin=margin, processes=2)
    for m, f in zip(robots[:3], found):
        assert f == selfcontact.search_pairs(selfcontact.kinematics(compile_model(m)), margin=margin)
    assert processes.processes_for(processes.PARALLEL_FROM - 1) == 1 == processes.processes_for(499, 500)


def test_a_background_thread_and_its_processes_run_below_the_callers_priority():
    """lower_thread_priority raises the nice value of the calling thread alone (Linux), and the processes it starts
    afterwards (an env build's pool) inherit it: a preparation in a background thread yields the cores to training."""
    import os
    import sys
    import threading
    if not sys.platform.startswith("linux"):
        pytest.skip("thread priorities are set on Linux only")
    main = os.getpriority(os.PRIO_PROCESS, 0)
    seen = {}

    def background():
        seen["lowered"] = processes.lower_thread_priority(3)
        seen["thread"] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        seen["children"] = processes.process_map(os.nice, [0, 0], 2, "nice values")
    t = threading.Thread(target=background)
    t.start()
    t.join()
    assert seen["lowered"] and seen["thread"] == main + 3 and seen["children"] == [main + 3] * 2
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == main


def test_searches_are_kept_on_disk_for_other_processes(tmp_path, monkeypatch):
    """With $MJX_MORPH_PAIR_CACHE set, a search is written there and read back instead of searched again (another
    process starts with an empty memory cache); other settings miss; an unreadable file is searched again with a
    warning and rewritten; set empty, nothing is written."""
    c, s = np.cos(np.radians(20.0)), np.sin(np.radians(20.0))     # limbs 0 and 1 touch, 2 is far from both
    m = Morphology(name="kept", height=0.5, limbs=(_limb(0, (0.0, 0.1, 0.0), (0.0, 0.2, 0.0)),
                                                   _limb(1, (0.0, 0.1 * c, 0.1 * s), (0.0, 0.2 * c, 0.2 * s)),
                                                   _limb(2, (0.1, 0.0, 0.0), (0.3, 0.0, 0.0))))
    margin = 0.0137                                        # settings no other test uses
    monkeypatch.setenv(selfcontact.PAIR_CACHE_ENV, str(tmp_path / "pairs"))
    monkeypatch.setattr(selfcontact, "_FOUND", {})
    first = selfcontact.robot_pairs(m, margin=margin)
    files = list((tmp_path / "pairs").glob("*.json"))
    assert len(files) == 1 and first.touching

    def no_search(*args, **kwargs):
        raise AssertionError("searched, though the search was kept on disk")
    monkeypatch.setattr(selfcontact, "_FOUND", {})         # another process: nothing in memory
    monkeypatch.setattr(selfcontact, "_search_all", no_search)
    assert selfcontact.robot_pairs(m, margin=margin) == first
    with pytest.raises(AssertionError, match="searched"):
        selfcontact.robot_pairs(m, margin=margin * 2)      # other settings: another file
    monkeypatch.undo()

    monkeypatch.setenv(selfcontact.PAIR_CACHE_ENV, str(tmp_path / "pairs"))
    monkeypatch.setattr(selfcontact, "_FOUND", {})
    files[0].write_text('{"candidates": [[1, 2]], "touch')  # a file cut short
    with pytest.warns(RuntimeWarning, match="unreadable kept self-collision pair search"):
        assert selfcontact.robot_pairs(m, margin=margin) == first
    assert json.loads(files[0].read_text())["boxes"] == first.boxes

    monkeypatch.setenv(selfcontact.PAIR_CACHE_ENV, "")
    monkeypatch.setattr(selfcontact, "_FOUND", {})
    assert selfcontact.pair_cache_dir() is None
    selfcontact.robot_pairs(m, margin=margin * 3)
    assert len(list((tmp_path / "pairs").glob("*"))) == 1
