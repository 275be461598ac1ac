"""Fidelity: padded robots in the stacked MJX model against the same robots alone in MuJoCo C (CPU, 2 robots).
The whole-set check is `python -m experiments.check_sim SET` (docs/benchmarks.md has the numbers)."""
from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx
from mujoco.mjx._src import collision_driver
from mujoco.mjx._src.types import GeomType

from mjx_morph.run import FAST_COMPILE
from mjx_morph.sim import contact, cpu_linalg, fidelity, terrain
from mjx_morph.sim.padding import SolverOptions
from sim_reference import available_robots


def _robots(n: int):
    rs = available_robots()
    out = []
    for m in rs:
        if not out or m.num_limbs != out[-1].num_limbs:
            out.append(m)
        if len(out) == n:
            return out
    return out


def test_padded_mjx_matches_mujoco_c_at_default_settings():
    """Padded MJX within 1e-3 m of each robot alone in MuJoCo C, and the padding's own share within issue 12's
    1e-5 m both in MuJoCo C (float64) and in MJX (padded against the robot alone, both float32)."""
    res = fidelity.compare(_robots(2), SolverOptions(), steps=25, compiler_options=FAST_COMPILE, unpadded_mjx=True)
    for r in res:
        assert r.error < fidelity.TOLERANCE, (r.name, r.error)
        assert r.padding < 1e-5, (r.name, r.padding)
        assert 0.0 < r.padding_mjx < 1e-5, (r.name, r.padding_mjx)
        assert 0.0 < r.mjx_alone < fidelity.TOLERANCE, (r.name, r.mjx_alone)
        assert 0.0 < r.mjx_ulp < fidelity.TOLERANCE, (r.name, r.mjx_ulp)     # float32's own spread: not nothing
    # a slice of the robots alone in MJX: the others are not run (NaN, left out of summaries), the slice's robot gets
    # exactly its values of the whole run (same start, actions and nudges), so slices of a long check add up
    sliced = fidelity.compare(_robots(2), SolverOptions(), steps=25, compiler_options=FAST_COMPILE, unpadded_mjx=True,
                              alone=range(1, 2))
    assert np.isnan([sliced[0].padding_mjx, sliced[0].mjx_alone, sliced[0].mjx_ulp]).all()
    for f in ("error", "padding", "padding_mjx", "mjx_alone", "mjx_ulp"):
        assert getattr(sliced[1], f) == getattr(res[1], f), f
    assert fidelity.summary([r.padding_mjx for r in sliced])["max"] == res[1].padding_mjx


def test_a_flat_contact_budget_above_the_touching_contacts_changes_nothing():
    """`env.flat_contact_budget` = K on ft: MJX keeps the K deepest of the env's contact slots (MJX's
    `max_contact_points`), so the solver has 4 K contact rows instead of 4 per slot. With K above the contacts that
    touch at once (session 34 counted at most 10 in MuJoCo C, 100 train robots x 20 s of random actions), padded
    MJX stays where it is without a budget: within float32's spread (~1e-6 m here, measured with and without K =
    12) of the same padded model in MuJoCo C, which keeps every contact; with K = 1 it cannot hold the robots up."""
    from mjx_morph.sim.env import EnvConfig, UnimalEnv
    robots = _robots(2)
    for k, want in ((0, None), (12, 12)):
        env = UnimalEnv(robots, EnvConfig(task="ft", flat_contact_budget=k))
        ncon = mjx.make_data(env.sm.model_for(0), impl="jax")._impl.contact.dist.shape[0]
        assert (ncon == want) if want else ncon > 12, (k, ncon)
    with pytest.raises(ValueError, match="env.flat_contact_budget=-1"):
        UnimalEnv(robots, EnvConfig(task="ft", flat_contact_budget=-1))
    # with a budget (here one above every slot, so all are kept), the unused slots' contacts (inside their parent's
    # geom, at a negative raw distance in some poses) are ranked last; without one their raw distances are left alone
    seen = 0
    for budget in (0, 200):
        env = UnimalEnv(robots, EnvConfig(task="ft", flat_contact_budget=budget))
        with contact.floor("box"):
            collide = jax.jit(lambda m, d: mjx.collision(m, mjx.kinematics(m, d)))
            for r in range(len(robots)):
                m = env.sm.model_for(r)
                c = collide(m, mjx.make_data(m, impl="jax"))._impl.contact
                margin = np.asarray(m.geom_margin)[np.asarray(c.geom)].sum(axis=1)
                never, dist = margin < contact.NEVER_ACTIVE, np.asarray(c.dist)
                seen += never.sum()
                assert (dist[~never] < contact.INACTIVE).any(), r
                if budget:
                    assert (dist[never] == contact.INACTIVE).all(), r
                elif never.any():
                    assert (dist[never] != contact.INACTIVE).all(), r          # the colliders' raw distances
    assert seen > 0                      # the two robots differ in limbs: one has unused slots
    for r in fidelity.compare(robots, SolverOptions(contact_budget=12), steps=25, compiler_options=FAST_COMPILE):
        assert r.mjx < 1e-4 and r.error < fidelity.TOLERANCE, (r.name, r.mjx, r.error)
        assert 1 < r.contacts <= 12, (r.name, r.contacts)       # MuJoCo C's most touching contacts: under the budget
    for r in fidelity.compare(robots, SolverOptions(contact_budget=1), steps=25, compiler_options=FAST_COMPILE):
        assert r.error > fidelity.TOLERANCE, (r.name, r.error)


def test_float64_mjx_isolates_the_padding():
    """With MJX in float64 (`x64=True`) the padded-vs-alone comparison in MJX carries no float32 rounding: one ulp of
    the start state moves the robot by ~1e-15 m, and the padding's share in MJX is the one MuJoCo C (float64) shows
    (measured 1.1e-7 against 1.1e-7 m), so issue 12's bound on the padding's own error is checked in MJX itself."""
    (r,) = fidelity.compare(_robots(1), SolverOptions(), steps=25, compiler_options=FAST_COMPILE, unpadded_mjx=True,
                            x64=True)
    assert r.mjx_ulp < 1e-12, r.mjx_ulp
    assert 0.0 < r.padding_mjx < 1e-5, r.padding_mjx
    assert abs(r.padding_mjx - r.padding) < 0.05 * r.padding, (r.padding_mjx, r.padding)
    assert jnp.zeros(()).dtype == jnp.float32          # the context ends with the call


def test_incline_matches_mujoco_c_on_metamorphs_slab(capsys):
    """The incline env's padded MJX against the same padded model in MuJoCo C on MetaMorph's slab box, in the
    env's frame (the torso starts at the origin; in MetaMorph's frame, 72 m away, float32 took 1 of 50 train robots
    over 1e-3 m and the median to 4.7e-5 m: docs/benchmarks.md, session 13). The bound is 2e-4 m: the second robot
    leaves MuJoCo C after a contact change at control step ~15 and drifts linearly to 9.1e-5 m (XLA's default CPU
    flags) or 1.09e-4 m (the suite's, fusion emitters off) by step 25 on an AVX-512 CPU, while MuJoCo C restarted
    from MJX's state before every control step lands within 1.3e-7 m of MJX's next state (`mjx_step`): float32's
    per-step rounding and the robot-robot contact gap, amplified (in float64, with MuJoCo C given the gap, the
    engines agree to ~1e-7 m: the next test). So the step-by-step bound is the tight one."""
    robots = _robots(2)
    res = fidelity.compare_task(robots, "incline", SolverOptions(), steps=25, trace=[robots[1].name])
    assert len(res) == 2
    for r in res:
        assert 0.0 < r.mjx < 2e-4, (r.name, r.mjx)
        assert 0.0 < r.mjx_step < 1e-5, (r.name, r.mjx_step)
        assert 0.0 < r.mjx_ulp < 1e-4, (r.name, r.mjx_ulp)     # the nudged start ran, and stayed near
        assert r.steps.shape == r.ulp_steps.shape == r.step_steps.shape == (25,)
        substeps = r.ncon.shape[2]
        assert r.ncon.shape == (25, 2, substeps) and r.ncon.min() >= 0 and r.ncon.max() > 0   # a robot on its slab
        # the restart and the run start control step 0 from one state: the same contacts in its first substep
        assert r.ncon[0, 0, 0] == r.ncon[0, 1, 0], r.ncon[0]
    assert res[0].contacts is None                               # kept for the traced robot only
    trace = res[1].contacts
    assert len(trace) == 25 and all(len(side) == res[1].ncon.shape[2] for step in trace for side in step)
    assert [[len(c) for c in side] for side in trace[7]] == res[1].ncon[7].tolist()
    assert any(g1 == "floor" or g2 == "floor" for step in trace for side in step for sub in side
               for _, g1, g2 in sub), "no floor contact in the trace"
    from experiments import check_sim                           # check_sim trace=[...] prints it step by step
    check_sim.print_trace(res[1])
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 1 + 25 + 1 + 2 * res[1].ncon.shape[2]
    t = int(np.argmax(res[1].step_steps))
    assert sum("<- largest step error" in ln for ln in lines) == 1 and "<- largest step error" in lines[1 + t]
    assert f"contacts at control step {t} " in lines[26]


def test_incline_in_float64_is_mujoco_c_but_for_the_gap():
    """`compare_task(x64=True)`: the env traced in float64 (its observations stay float32) from the start a float32
    run has. Without float32's rounding a one-ulp nudge stays at ~1e-14 m, and with MuJoCo C given MJX's robot-robot
    contact gap (`c_gap`) the two engines step alike: ~1e-10 m a control step, one step of the second robot at
    1.9e-8 m (the same contacts in both, every substep's qacc from MuJoCo C's state within 3e-11: the Newton
    solver's stopping tolerance, as at 100 / 50 iterations), trajectories within ~1e-7 m. Before session 42's
    capsule colliders (MJX's own, which project with |d|^2 + 1e-6) the steps differed by ~1.5e-7 m and a
    trajectory ended 7.6e-5 m away (docs/benchmarks.md, "CPU notes")."""
    res = fidelity.compare_task(_robots(2), "incline", SolverOptions(), steps=25, x64=True, c_gap=True)
    for r in res:
        assert 0.0 < r.mjx < 1e-6, (r.name, r.mjx)
        assert 0.0 < np.median(r.step_steps) < 1e-9 and r.mjx_step < 5e-8, (r.name, r.step_steps)
        assert 0.0 < r.mjx_ulp < 1e-10, (r.name, r.mjx_ulp)
        assert r.ncon[:, 0].max() >= 2, r.name              # contacts were made (floor and self)
    assert jnp.zeros(()).dtype == jnp.float32          # the context ends with the call


def test_the_default_solver_solves_what_mujocos_defaults_solve():
    """The env's Newton cap (`EnvConfig.iterations`) never stops the solve: each robot alone in MuJoCo C steps at it
    exactly as at MuJoCo's defaults (100 / 50, MetaMorph's MuJoCo 2.0; `fidelity.converged`), 25 control steps of
    N(0, 0.9) actions on MetaMorph's floor. At 5 iterations (the cap until session 43) the solve stops unconverged
    and robots move apart by millimetres to centimetres within 0.5 s: MuJoCo C's own truncation, which a check of
    MJX against MuJoCo C at equal settings cannot see (`check_sim SET c_defaults=true` measures it in MJX)."""
    from mjx_morph.sim.env import EnvConfig
    cap = EnvConfig().iterations
    assert SolverOptions().iterations == cap                      # one default for the env and the checks
    rng = np.random.default_rng(0)
    truncated = []
    for m in available_robots()[:40]:
        base = fidelity.alone_model(m, SolverOptions(), fidelity.METAMORPH_FLOOR)
        q = base.qpos0 + rng.uniform(-0.005, 0.005, base.nq)
        v = rng.uniform(-0.005, 0.005, base.nv)
        a = rng.normal(0.0, 0.9, (25, base.nu))
        x = {}
        for it in (5, cap, 100):
            mm = fidelity.alone_model(m, SolverOptions(iterations=it), fidelity.METAMORPH_FLOOR)
            if it == 100:
                fidelity.converged([mm])
                assert (mm.opt.iterations, mm.opt.ls_iterations) == fidelity.MUJOCO_SOLVER
            x[it], _ = fidelity._run_c(mm, q, v, a, 4, np.arange(1, 1 + m.num_nodes))
        assert np.abs(x[cap] - x[100]).max() < 1e-12, m.name
        truncated.append(np.abs(x[5] - x[100]).max())
    assert sum(e > 1e-3 for e in truncated) >= 2, sorted(truncated)[-5:]


def test_ft_in_float64_is_mujoco_c_but_for_the_gap():
    """`compare(x64=True, c_gap=True)`: padded MJX in float64 against the same padded robot in MuJoCo C given MJX's
    robot-robot contact gap (MetaMorph's box floor there, its rule in MJX): the engines agree to ~1e-15 m (median
    of the 100 train robots; at most 2.8e-7 m). Without the gap in MuJoCo C they are ~1e-6 m apart: the gap's own
    share, which moved one train robot by 3.9e-3 m (a limb-limb contact within 1e-7 m of touching; session 43)."""
    robots = _robots(2)
    with_gap = fidelity.compare(robots, SolverOptions(), steps=25, x64=True, c_gap=True)
    without = fidelity.compare(robots, SolverOptions(), steps=25, x64=True)
    for r, w in zip(with_gap, without):
        assert r.mjx < 1e-10, (r.name, r.mjx)
        assert r.padding < 1e-5, (r.name, r.padding)
        assert w.mjx > 1e3 * max(r.mjx, 1e-13), (r.name, w.mjx, r.mjx)    # the gap's share is what is left
    assert jnp.zeros(()).dtype == jnp.float32


def test_terrains_are_the_same_under_float64():
    """A float64 fidelity check (`x64=true`) runs on the terrain a float32 run draws from the same key: the
    generators draw int32 indices and float32 values whatever `jax.enable_x64` says."""
    from mjx_morph.sim.terrain import corridor, obstacles
    for key in jax.random.split(jax.random.PRNGKey(5), 3):
        for gen in (corridor.generate, obstacles.generate):
            a = jax.tree_util.tree_leaves(gen(key))
            with jax.enable_x64(True):
                b = jax.tree_util.tree_leaves(gen(key))
            for x, y in zip(a, b):
                assert x.dtype == y.dtype and np.array_equal(np.asarray(x), np.asarray(y)), gen


@pytest.mark.parametrize("incline", [0.0, 10.0])
def test_reference_floor_is_the_simulated_surface(incline):
    """MetaMorph's floor box (`reference_world`, MuJoCo C references) has its top face on the simulated plane, and
    the robot starts on it at the origin: MuJoCo C puts a point on the plane at distance 0 from the box."""
    t = terrain.Plane() if not incline else terrain.InclinedPlane(incline_deg=incline)
    xml = ('<mujoco><worldbody>' + t.world().geoms.replace('name="floor"', 'name="plane"')
           + t.reference_world().geoms.replace('name="floor"', 'name="box"')
           + '<body pos="0 0 0"><freejoint/><geom name="ball" type="sphere" size="0.01"/></body></worldbody></mujoco>')
    mm = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(mm)
    a = np.radians(incline)
    normal = np.array([-np.sin(a), 0.0, np.cos(a)])         # the plane's normal: euler (0, -a, 0), uphill +x
    for x, y in [(0.0, 0.0), (1.5, -2.0), (-1.5, 4.0)]:          # on the slab (it ends 2 m behind the start)
        # MetaMorph's slab top z = 1/cos(a) + tan(a) x, in the env's frame (its origin on the slab at the start)
        on_plane = np.array([x, y, np.tan(a) * x + 1 / np.cos(a) - 1]) if incline else np.array([x, y, 0.0])
        d.qpos[:3] = on_plane + 0.01 * normal               # the ball resting on the surface
        mujoco.mj_forward(mm, d)
        for geom in ("plane", "box"):
            dist = mujoco.mj_geomDistance(mm, d, mm.geom(geom).id, mm.geom("ball").id, 1.0, None)
            assert abs(dist) < 1e-9, (incline, geom, x, y, dist)


def test_ulp_nudge_moves_every_entry_one_float32_step():
    x = np.random.default_rng(0).normal(size=1000) * np.logspace(-3, 2, 1000)
    y = fidelity.ulp_nudge(x, np.random.default_rng(1))
    x32 = x.astype(np.float32)
    assert y.dtype == np.float32 and (y != x32).all()
    # adjacent float32 values: their gap is the spacing above the smaller magnitude
    gap = np.spacing(np.minimum(np.abs(x32), np.abs(y)))
    np.testing.assert_array_equal(np.abs(y.astype(np.float64) - x32.astype(np.float64)), gap.astype(np.float64))
    assert 0.3 < (y > x32).mean() < 0.7


def _order(c):
    """Contacts ordered by distance, then position (two ends lying on the floor have equal distances)."""
    return round(float(c[0]), 5), tuple(np.round(np.asarray(c[1], np.float64), 4))


def _c_contacts(floor_xml: str, pos, quat, length: float, radius: float):
    """MuJoCo C's contacts of one free capsule with the floor: (dist, pos, normal up, first tangent) sorted by dist."""
    xml = (f'<mujoco><worldbody>{floor_xml}<body pos="{float(pos[0])!r} {float(pos[1])!r} {float(pos[2])!r}" '
           f'quat="{" ".join(repr(float(x)) for x in quat)}"><freejoint/>'
           f'<geom type="capsule" fromto="0 0 0 {float(length)!r} 0 0" size="{float(radius)!r}"/></body></worldbody></mujoco>')
    mm = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(mm)
    mujoco.mj_forward(mm, d)
    out = []
    for c in d.contact[:d.ncon]:
        f = np.array(c.frame).reshape(3, 3)
        sign = 1.0 if c.geom[0] == 0 else -1.0              # the normal points from geom1 to geom2
        out.append((c.dist, np.array(c.pos), sign * f[0], f[1]))
    return mm, d, sorted(out, key=_order)


@pytest.mark.parametrize("incline", [0.0, 10.0])
def test_floor_contacts_equal_mujoco_c(incline):
    """The installed (plane, capsule) collider: rule "box" gives MuJoCo C's contacts against MetaMorph's box floor
    (distances, points, and the frame up to the signs of its axes), rule "plane" MuJoCo C's against a plane (first
    tangent = the capsule axis projected), "mjx" MJX's own; random capsule poses on ft's and incline's floors."""
    collide = collision_driver._COLLISION_FUNC[(GeomType.PLANE, GeomType.CAPSULE)]
    assert collide.never_ranked and collide.ncon == contact._floor_capsule.ncon     # the rule, unused slots ranked last
    a = np.radians(incline)
    plane = terrain.Plane() if not incline else terrain.InclinedPlane(incline_deg=incline)
    plane_xml = plane.world().geoms.replace(' contype="0" conaffinity="1"', "")
    # MetaMorph's floor box (centred at its world's origin, top face z = 1/cos(a) + tan(a) x) in the env's frame,
    # whose origin is MetaMorph's `origin` (longer than the incline's 150 m slab, to reach the env's start)
    ox, oy, oz = plane.origin
    box_xml = (f'<geom type="box" size="100 {20 if incline else 100} 1" pos="{-ox!r} {-oy!r} {-oz!r}" '
               f'euler="0 {-incline!r} 0"/>')

    def top(x):             # the floor's top at x (the env's frame)
        return 1 / np.cos(a) + np.tan(a) * (x + ox) - oz
    rng = np.random.default_rng(0)
    seen = {1: 0, 2: 0}
    for i in range(40):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        length, radius = rng.uniform(0.05, 0.4), rng.uniform(0.03, 0.07)
        x = rng.uniform(-3, 3)
        pos = (x, rng.uniform(-3, 3), top(x) + rng.uniform(-0.05, 0.2))
        if i % 4 == 0:          # lying on the floor, both ends' centres above it: MuJoCo C gives two contacts
            t = rng.uniform(0, 2 * np.pi)
            q = np.array([np.cos(t / 2), 0.0, 0.0, np.sin(t / 2)])
            tilt = np.array([np.cos(-a / 2), 0.0, np.sin(-a / 2), 0.0])     # lie along the incline's face
            lying = np.zeros(4)
            mujoco.mju_mulQuat(lying, tilt, q)
            q = lying
            pos = (x, pos[1], top(x) + (radius - 0.01) / np.cos(a))
        mm, d, want = _c_contacts(box_xml, pos, q, length, radius)
        pm, pd, want_plane = _c_contacts(plane_xml, pos, q, length, radius)
        m = mjx.put_model(pm, impl="jax")
        dx = mjx.kinematics(m, mjx.put_data(pm, pd, impl="jax"))
        pair = jnp.asarray([[0, 1]])
        for rule, ref in [("box", want), ("plane", want_plane)]:
            with contact.floor(rule):
                dist, cpos, frame = (np.asarray(v) for v in collide(m, dx, None, pair))
            got = sorted([(dist[k], cpos[k], frame[k]) for k in range(2) if dist[k] < 0], key=_order)
            assert len(got) == len(ref), (rule, i, [g[0] for g in got], [w[0] for w in ref])
            for g, w in zip(got, ref):
                assert abs(g[0] - w[0]) < 1e-5 and np.abs(g[1] - w[1]).max() < 1e-5, (rule, i)
                np.testing.assert_allclose(g[2][0], w[2], atol=1e-5)                 # normal, pointing up
                np.testing.assert_allclose(np.abs(g[2][1] @ w[3]), 1.0, atol=1e-5)   # first tangent, up to sign
            if rule == "box" and ref:
                seen[len(ref)] += 1
        with contact.floor("plane"):
            plane_dist = np.asarray(collide(m, dx, None, pair)[0])
        with contact.floor("mjx"):
            mjx_dist = np.asarray(collide(m, dx, None, pair)[0])
        np.testing.assert_allclose(np.sort(mjx_dist), np.sort(plane_dist), atol=1e-6)    # same points, own frames
    assert seen[1] and seen[2], seen          # both a one-contact and a two-contact case were checked
    with pytest.raises(ValueError, match="floor_contacts='boxes'"):
        with contact.floor("boxes"):
            pass


def _two_geoms(kinds, poses, sizes):
    """Two free geoms (sphere or capsule along the body's x axis) at `poses` ((pos, quat) each), for MuJoCo C."""
    bodies = []
    for kind, (pos, quat), (radius, length) in zip(kinds, poses, sizes):
        shape = (f'type="capsule" fromto="{-length!r} 0 0 {length!r} 0 0" size="{radius!r}"' if kind == "capsule"
                 else f'type="sphere" size="{radius!r}"')
        bodies.append(f'<body pos="{" ".join(repr(float(x)) for x in pos)}" '
                      f'quat="{" ".join(repr(float(x)) for x in quat)}"><freejoint/><geom {shape}/></body>')
    return mujoco.MjModel.from_xml_string(f"<mujoco><worldbody>{''.join(bodies)}</worldbody></mujoco>")


@pytest.mark.parametrize("kinds", [("capsule", "capsule"), ("sphere", "capsule")])
def test_robot_robot_contacts_equal_mujoco_c(kinds):
    """The installed limb-limb (capsule-capsule) and torso-limb (sphere-capsule) colliders make MuJoCo C's contact:
    distance, point and frame to 1e-12 in float64 (MJX's own colliders are ~1e-6 m off in the point, their segment
    projections divide by |d|^2 + 1e-6), and to float32's precision in float32; random poses, the general case with
    every clipping branch and, for two capsules, parallel axes (MuJoCo C makes up to two contacts there; the one
    slot holds the deeper)."""
    key = tuple(GeomType.SPHERE if k == "sphere" else GeomType.CAPSULE for k in kinds)
    collide = collision_driver._COLLISION_FUNC[key]
    assert collide.never_ranked and collide.ncon == 1
    rng = np.random.default_rng(1)
    seen = {"general": 0, "parallel": 0, "clipped": 0}
    for i in range(40):
        sizes = [(rng.uniform(0.03, 0.07), rng.uniform(0.05, 0.2)) for _ in kinds]
        quats = [q / np.linalg.norm(q) for q in rng.normal(size=(2, 4))]
        parallel = kinds[0] == "capsule" and i % 5 == 0
        if parallel or kinds[0] == "sphere":     # capsules side by side, overlapping or not; the sphere beside the
            quats[1] = quats[0].copy()           # capsule's axis or beyond its end
        x0 = np.zeros(3)
        mat = np.zeros(9)
        mujoco.mju_quat2Mat(mat, quats[0])
        side = np.cross(mat.reshape(3, 3)[:, 0], rng.normal(size=3))
        offset = (side / np.linalg.norm(side) * (sizes[0][0] + sizes[1][0] - rng.uniform(0.0, 0.02))
                  + mat.reshape(3, 3)[:, 0] * rng.uniform(-0.3, 0.3) * (0.5 if parallel else 1.0))
        mm = _two_geoms(kinds, [(x0, quats[0]), (offset, quats[1])], sizes)
        d = mujoco.MjData(mm)
        mujoco.mj_forward(mm, d)
        if d.ncon == 0:
            continue
        seen["parallel" if parallel else "general"] += 1
        for dtype, tol in ((np.float64, 1e-12), (np.float32, 3e-6)):
            with jax.enable_x64(dtype == np.float64):
                m = mjx.put_model(mm, impl="jax")
                dx = mjx.kinematics(m, mjx.make_data(m, impl="jax").replace(qpos=jnp.asarray(d.qpos, dtype)))
                dist, cpos, frame = (np.asarray(v)[0] for v in collide(m, dx, None, jnp.asarray([[0, 1]])))
            assert dist.dtype == dtype
            # parallel axes: one of C's contacts (C orders a pair's contacts in no fixed way), the deepest
            want = min(d.contact[:d.ncon], key=lambda c: (c.dist > dist + tol, np.abs(c.pos - cpos).max()))
            assert abs(dist - min(d.contact.dist[:d.ncon])) < tol, (i, dtype)
            assert abs(dist - want.dist) < tol and np.abs(cpos - want.pos).max() < tol, (i, dtype, dist, want.dist)
            np.testing.assert_allclose(frame.ravel(), np.asarray(want.frame), atol=tol * 10, err_msg=f"{i} {dtype}")
        if not parallel:        # the contact beyond a segment's end: a clipped parameter
            g = 0 if kinds[0] == "capsule" else 1
            half = np.asarray(mm.geom_size[g][1] * d.geom_xmat[g].reshape(3, 3)[:, 2])
            seen["clipped"] += abs((want.pos - d.geom_xpos[g]) @ half / (half @ half)) > 0.99
    assert seen["general"] > 8 and seen["clipped"] > 2, seen
    assert kinds[0] == "sphere" or seen["parallel"] > 3, seen


def test_cpu_cholesky_matches_lapack():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(4, 12, 12))
    a = a @ a.transpose(0, 2, 1) + 12 * np.eye(12)
    b = rng.normal(size=(4, 12))
    c, low = cpu_linalg.cho_factor(a)
    np.testing.assert_allclose(np.asarray(c), np.linalg.cholesky(a).transpose(0, 2, 1), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(np.asarray(cpu_linalg.cho_solve((c, low), b)), np.linalg.solve(a, b[..., None])[..., 0],
                               rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("kind", ["corridor", "obstacles"])
def test_height_field_patch_is_the_observed_terrain(kind):
    """MuJoCo C ray casts on the physical height-field patch hit the terrain function's cell heights."""
    terr = terrain.KINDS[kind](patch_size=41)
    world = terr.world()
    asset, geom = world.assets, world.geoms
    ts = terr.generate(jax.random.PRNGKey(5))
    rng = np.random.default_rng(0)
    for x0, y0 in [(rng.uniform(0, 90), rng.uniform(-18, 18)) for _ in range(3)] + [(95.5, 19.0)]:
        data, pos = jax.jit(terr.patch)(ts, x0, y0)
        g = geom.replace(f'pos="0 0 {terrain.grid.Z_LO:g}"', 'pos="{} {} {}"'.format(*np.asarray(pos, np.float64)))
        mm = mujoco.MjModel.from_xml_string(f"<mujoco><asset>{asset}</asset><worldbody>{g}</worldbody></mujoco>")
        mm.hfield_data[:] = np.asarray(data)
        d = mujoco.MjData(mm)
        mujoco.mj_forward(mm, d)
        ct, rt = terrain.grid.cell_of(np.float32(x0), np.float32(y0))
        for dc, dr in [(0, 0), (7, -3), (-12, 15), (18, 18), (-18, -17)]:
            c, r = int(ct) + dc, int(rt) + dr
            x = -3 + c / 10 + 0.05
            y = (200 - r) / 10 + 0.05
            geomid = np.zeros(1, np.int32)
            dist = mujoco.mj_ray(mm, d, np.array([x, y, 20.0]), np.array([0, 0, -1.0]), None, 1, -1, geomid)
            want = float(terr.physical_height(ts, np.int32(c), np.int32(r)))
            assert abs((20.0 - dist) - want) < 1e-4, (kind, x, y, 20.0 - dist, want)


def test_check_sim_slices_the_alone_runs_and_writes_csv(tmp_path, capsys):
    """`check_sim ... unpadded_range=lo:hi csv=F`: only robots lo..hi-1 run alone in MJX (the others print nan), one
    CSV row per robot; a malformed or out-of-range slice, or a slice without unpadded_mjx, is a clear error."""
    import csv
    from experiments import check_sim
    from mjx_morph.sim.env import EnvConfig
    out = tmp_path / "rows.csv"
    args = ["gen/train", "num_robots=2", "steps=5", "unpadded_mjx=true"]
    assert check_sim.main([*args, "unpadded_range=1:2", f"csv={out}"]) == 0
    text = capsys.readouterr().out
    assert f"contact budget {EnvConfig().flat_contact_budget}" in text          # the env's default budget
    assert int(re.search(r"contacts touching at once.* max (\d+) ", text)[1]) >= 1
    rows = list(csv.DictReader(out.read_text().splitlines()))
    assert len(rows) == 2 and rows[0]["padding_mjx"] == "nan" and float(rows[1]["padding_mjx"]) < 1e-3
    assert all(float(r["error"]) < fidelity.TOLERANCE for r in rows)
    for bad, msg in (("2:1", "expected 0 <= lo < hi <= 2"), ("1-2", "expected lo:hi")):
        assert check_sim.main([*args, f"unpadded_range={bad}"]) == 2
        assert msg in capsys.readouterr().err
    assert check_sim.main(["gen/train", "num_robots=2", "unpadded_range=0:1"]) == 2
    assert "needs unpadded_mjx=true" in capsys.readouterr().err
    assert check_sim.main(["gen/train", "num_robots=2", "task=incline", "trace=[no-such-robot]"]) == 2
    assert "trace='no-such-robot'" in capsys.readouterr().err
    assert check_sim.main(["gen/train", "num_robots=2", "trace=[gen-0-0]"]) == 2      # ft: no trace
    assert "needs task=incline, csr or obstacle" in capsys.readouterr().err
    assert check_sim.main([f"merge=[{out},{out}]"]) == 0          # the same slice twice: its own values agree
    assert "1 of 2 robots run alone in MJX" in capsys.readouterr().out


def test_check_sim_merges_the_slices_of_one_check(tmp_path, capsys):
    """`check_sim merge=[a.csv,b.csv]`: each robot's alone columns from the slice that ran it, the padded columns
    checked equal (the same check); other robots, other padded values, a robot run twice with other values, or a
    file that is no check_sim CSV are clear errors."""
    import csv
    from experiments import check_sim
    head = ["robot", "iterations", "ls_iterations", *check_sim.PADDED, *check_sim.ALONE]
    padded = {"r0": ["1e-6", "2e-7", "1e-6", "3e-7"], "r1": ["2e-3", "2e-7", "2e-3", "3e-3"], "r2": ["4e-6"] * 4}
    alone = {"r0": ["5e-7", "1e-6", "6e-7"], "r1": ["4e-7", "2e-3", "5e-7"]}

    def write(name, measured, rows=padded):
        with (tmp_path / name).open("w", newline="") as fh:
            csv.writer(fh).writerows([head] + [[r, 5, 8, *v, *(alone[r] if r in measured else ["nan"] * 3)]
                                               for r, v in rows.items()])
        return str(tmp_path / name)

    a, b = write("a.csv", {"r0"}), write("b.csv", {"r1"})
    out = tmp_path / "all.csv"
    with pytest.raises(SystemExit) as stop:                              # r1 is over 1e-3 m padded: exit 1
        check_sim.main([f"merge=[{a},{b}]", f"csv={out}"])
    assert stop.value.code == 1
    printed = capsys.readouterr().out
    assert "2 of 3 robots run alone in MJX" in printed and "# mjx_alone: 1 of 2 over 0.001 m: r1 (2.00e-03)" in printed
    rows = {r["robot"]: r for r in csv.DictReader(out.read_text().splitlines())}
    assert rows["r0"]["mjx_alone"] == "1e-6" and rows["r1"]["mjx_alone"] == "2e-3" and rows["r2"]["mjx_alone"] == "nan"
    other = write("other.csv", {"r1"}, {**padded, "r2": ["5e-6"] * 4})
    fewer = write("fewer.csv", {"r1"}, {k: padded[k] for k in ("r0", "r1")})
    alone["r0"] = ["9e-7", "9e-7", "9e-7"]
    twice = write("twice.csv", {"r0"})
    (tmp_path / "x.csv").write_text("a,b\n1,2\n")
    for files, msg in (([a, other], "r2: error 5e-6 differs from"), ([a, fewer], "other columns or robots"),
                       ([a, twice], "was run alone in"), ([a, str(tmp_path / "x.csv")], "not a check_sim CSV"),
                       ([a, str(tmp_path / "none.csv")], "no such file")):
        assert check_sim.main([f"merge=[{','.join(files)}]"]) == 2
        assert msg in capsys.readouterr().err
    assert check_sim.main([]) == 2 and "set: required" in capsys.readouterr().err
