"""The height-field sphere / capsule collider installed into MJX (mjx_morph/sim/hfield_contact.py) against MuJoCo
C's `mjc_ConvexHField`: random poses of a free capsule and a free sphere over a small random height field, MJX's
own pipeline (put_model / make_data / collision) in float64, compared with MuJoCo C's d.contact after mj_forward."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx
from mujoco.mjx._src import collision_driver
from mujoco.mjx._src.types import GeomType

from mjx_morph.sim import hfield_contact

N, SIZE, ZS, BASE = 13, 0.6, 0.3, 0.1       # vertices per side, half size, height range, base of the field


def _model(capsule_size, sphere_radius) -> mujoco.MjModel:
    """A tilted, shifted height field, a free capsule and a free sphere (which do not collide with each other)."""
    xml = f"""<mujoco><asset><hfield name="hf" nrow="{N}" ncol="{N}" size="{SIZE} {SIZE} {ZS} {BASE}"/></asset>
      <worldbody><geom type="hfield" hfield="hf" pos="0.05 -0.03 0.2" euler="4 -3 30" contype="0" conaffinity="1"/>
        <body><freejoint/><geom type="capsule" size="{capsule_size[0]} {capsule_size[1]}" contype="1"
          conaffinity="0"/></body>
        <body><freejoint/><geom type="sphere" size="{sphere_radius}" contype="1" conaffinity="0"/></body>
      </worldbody></mujoco>"""
    return mujoco.MjModel.from_xml_string(xml)


def _c_contacts(mm, d, geom):
    cs = [c for c in d.contact[:d.ncon] if c.geom[1] == geom]
    return (np.array([c.dist for c in cs]), np.array([c.pos for c in cs]).reshape(-1, 3),
            np.array([c.frame for c in cs]).reshape(-1, 3, 3))


def _pose(rng, mm, d, body, radius, half, deep=False):
    """A random orientation, centred over the field's middle, lowest point from 1 cm above to 4 cm below the
    highest of the four vertices around it (`deep`: 0 to 4 cm deeper than the radius) (field's local frame)."""
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    hpos, hmat = d.geom_xpos[0], d.geom_xmat[0].reshape(3, 3)
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, q)
    axis = hmat.T @ mat.reshape(3, 3)[:, 2]
    xy = rng.uniform(-0.25, 0.25, 2)
    c, r = ((xy + SIZE) / (2 * SIZE) * (N - 1)).astype(int)
    top = mm.hfield_data.reshape(N, N)[r:r + 2, c:c + 2].max() * ZS
    z = top + radius + half * abs(axis[2]) - (rng.uniform(radius, radius + 0.04) if deep else rng.uniform(-0.01, 0.04))
    adr = mm.jnt_qposadr[mm.body_jntadr[body]]
    d.qpos[adr:adr + 3] = hmat @ np.array([xy[0], xy[1], z]) + hpos
    d.qpos[adr + 3:adr + 7] = q


def test_hfield_contacts_equal_mujoco_c():
    """Same number of contacts, in the same order, same distances, points and frames: to 1e-9 where MuJoCo C's
    GJK gives the exact closest points (penetration shallower than the radius), to EPA's tolerance where it runs
    EPA (the geom's core inside the prism: depth 2e-6, normal 1e-4, point 1e-3)."""
    assert isinstance(collision_driver._COLLISION_FUNC[(GeomType.HFIELD, GeomType.CAPSULE)],
                      hfield_contact._Installed)
    per_geom = 24
    rng = np.random.default_rng(0)
    checked = {"capsule": 0, "sphere": 0, "deep": 0}
    most = {"capsule": 0, "sphere": 0}
    with jax.enable_x64(True), hfield_contact.rule("mujoco", per_geom):
        mm = _model((0.08, 0.3), 0.1)     # the largest sizes drawn below: MJX's cell window is sized at put_model
        mx = mjx.put_model(mm, impl="jax")
        template = mjx.make_data(mx, impl="jax")
        assert template._impl.contact.dist.shape == (2 * per_geom,)

        @jax.jit
        def collide(hdata, gsize, qpos):
            m = mx.replace(hfield_data=hdata, geom_size=gsize)
            dx = collision_driver.collision(m, mjx.kinematics(m, template.replace(qpos=qpos)))
            c = dx._impl.contact
            return c.dist, c.pos, c.frame, c.geom

        for i in range(30):
            mm.hfield_data[:] = rng.uniform(0, 1, N * N) if i % 3 else np.where(rng.uniform(size=N * N) < .5, .3, .6)
            mm.geom_size[1, :2] = rng.uniform(0.02, 0.08), rng.uniform(0.05, 0.3)
            mm.geom_size[2, 0] = rng.uniform(0.02, 0.1)
            d = mujoco.MjData(mm)
            mujoco.mj_kinematics(mm, d)
            _pose(rng, mm, d, 1, mm.geom_size[1, 0], mm.geom_size[1, 1], deep=i % 5 == 4)
            _pose(rng, mm, d, 2, mm.geom_size[2, 0], 0.0, deep=i % 5 == 4)
            mujoco.mj_forward(mm, d)
            dist, pos, frame, geom = (np.asarray(x) for x in collide(jnp.asarray(mm.hfield_data),
                                                                      jnp.asarray(mm.geom_size), jnp.asarray(d.qpos)))
            for g, name in [(1, "capsule"), (2, "sphere")]:
                want = _c_contacts(mm, d, g)
                mine = (geom[:, 1] == g) & (dist < 1.0)
                assert mine.sum() == len(want[0]) <= per_geom, (i, name, mine.sum(), len(want[0]))
                most[name] = max(most[name], len(want[0]))
                got = dist[mine], pos[mine], frame[mine]
                deep = want[0] < -mm.geom_size[g, 0] + 1e-6
                for k, tol, tol_deep in [(0, 1e-9, 2e-6), (1, 1e-9, 1e-3), (2, 1e-9, 1e-4)]:
                    err = np.abs(got[k] - want[k]).reshape(len(want[0]), -1).max(axis=1, initial=0.0) \
                        if len(want[0]) else np.zeros(0)
                    assert np.all(err <= np.where(deep, tol_deep, tol)), (i, name, k, err, deep)
                checked[name] += int((~deep).sum())
                checked["deep"] += int(deep.sum())
    assert checked["capsule"] > 50 and checked["sphere"] > 20 and checked["deep"] > 0, checked
    assert most["capsule"] > 4 and most["sphere"] > 4, most        # more than MJX's own collider keeps


def test_rules_size_the_contact_arrays():
    """The rule of the block decides the contacts per pair MJX allocates: MJX's own 4, or `per_geom`."""
    mm = _model((0.05, 0.2), 0.06)
    with hfield_contact.rule("mjx"):
        assert len(collision_driver.make_condim(mm)) == 8
    with hfield_contact.rule("mujoco", 10):
        assert len(collision_driver.make_condim(mm)) == 20
    assert len(collision_driver.make_condim(mm)) == 2 * hfield_contact.DEFAULT_PER_GEOM
    with pytest.raises(ValueError, match="hfield_contacts='box'"):
        with hfield_contact.rule("box"):
            pass
