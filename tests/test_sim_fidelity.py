"""Fidelity: padded robots in the stacked MJX model against the same robots alone in MuJoCo C (CPU, 2 robots).
The whole-set check is `python -m experiments.check_sim SET` (docs/benchmarks.md has the numbers)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx
from mujoco.mjx._src import collision_driver
from mujoco.mjx._src.types import GeomType

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
    fast = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}
    res = fidelity.compare(_robots(2), SolverOptions(), steps=25, compiler_options=fast)
    for r in res:
        assert r.error < fidelity.TOLERANCE, (r.name, r.error)


def test_plane_capsule_frames_installed_once_and_chosen_per_trace():
    """Importing mjx_morph.sim put our (plane, capsule) collider into MJX's table: MuJoCo C's first tangent (the
    capsule axis projected onto the plane) by default, MJX's own frame inside `contact.frames(False)` (what an env
    with c_contact_frames=False traces its step in); contact distances and points are the same."""
    collide = collision_driver._COLLISION_FUNC[(GeomType.PLANE, GeomType.CAPSULE)]
    assert collide is contact._plane_capsule
    xml = ('<mujoco><worldbody><geom type="plane" size="0 0 1"/><body pos="0 0 0.2" axisangle="1 1 0 20">'
           '<freejoint/><geom type="capsule" size="0.05 0.2"/></body></worldbody></mujoco>')
    m = mjx.put_model(mujoco.MjModel.from_xml_string(xml), impl="jax")
    d = mjx.kinematics(m, mjx.make_data(m, impl="jax"))
    pair = jnp.asarray([[0, 1]])
    c_dist, c_pos, c_frame = (np.asarray(x) for x in collide(m, d, None, pair))
    with contact.frames(False):
        j_dist, j_pos, j_frame = (np.asarray(x) for x in collide(m, d, None, pair))
    axis = np.asarray(d.geom_xmat[1])[:, 2]
    tangent = np.array([axis[0], axis[1], 0.0]) / np.linalg.norm(axis[:2])     # steeper than 60 degrees
    np.testing.assert_allclose(c_frame[:, 1], [tangent, tangent], atol=1e-6)
    assert np.abs(j_frame[:, 1] - tangent).max() > 0.1                          # MJX: a fixed world axis
    np.testing.assert_allclose(c_frame[:, 0], j_frame[:, 0], atol=1e-6)         # same normal, points, distances
    np.testing.assert_allclose(c_pos, j_pos, atol=1e-6)
    np.testing.assert_allclose(c_dist, j_dist, atol=1e-6)
    assert collision_driver._COLLISION_FUNC[(GeomType.PLANE, GeomType.CAPSULE)] is collide


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
