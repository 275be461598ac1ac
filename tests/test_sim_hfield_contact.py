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
from mujoco.mjx._src import collision_driver, mesh
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


@pytest.mark.parametrize("candidates", [0, 64])
def test_hfield_contacts_equal_mujoco_c(candidates):
    """Same number of contacts, in the same order, same distances, points and frames: to 1e-9 where MuJoCo C's
    GJK gives the exact closest points (penetration shallower than the radius), to EPA's tolerance where it runs
    EPA (the geom's core inside the prism: depth 2e-6, normal 1e-4, point 1e-3). Every prism tested exactly
    (candidates 0), or only the 64 of lowest bound (`hfield_group`)."""
    assert isinstance(collision_driver._COLLISION_FUNC[(GeomType.HFIELD, GeomType.CAPSULE)],
                      hfield_contact._Installed)
    per_geom = 24
    rng = np.random.default_rng(0)
    checked = {"capsule": 0, "sphere": 0, "deep": 0}
    most = {"capsule": 0, "sphere": 0}
    with jax.enable_x64(True), hfield_contact.rule("mujoco", per_geom, candidates):
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


def test_bound_never_drops_a_contact():
    """`_bound` (the cheap test that picks the prisms `hfield_group` tests exactly) is below the slack for every
    prism that the exact test finds in contact, over 20,000 random capsules and spheres around random prisms, and
    still rules out most prisms that are not in contact."""
    rng = np.random.default_rng(1)
    n = 20000
    cell = np.array([0.1, 0.1])
    lo = rng.uniform(-1, 1, (n, 2))
    tops = np.zeros((n, 3, 3))
    corners = lo[:, None] + cell * np.array([[0, 1], [0, 0], [1, 1]])       # MuJoCo C's first prism of a cell
    second = rng.uniform(size=n) < 0.5
    corners[second] = lo[second, None] + cell * np.array([[0, 0], [1, 1], [1, 0]])
    tops[:, :, :2] = corners
    tops[:, :, 2] = rng.uniform(0.0, 0.3, (n, 3))
    radius = rng.uniform(0.02, 0.08, n)
    half = np.where(rng.uniform(size=n) < 0.2, 0.0, rng.uniform(0.05, 0.3, n))
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    centre = np.concatenate([lo + rng.uniform(-0.3, 0.4, (n, 2)), rng.uniform(-0.1, 0.6, (n, 1))], axis=1)
    a, b = centre - half[:, None] * axis, centre + half[:, None] * axis
    with jax.enable_x64(True):
        dist = jax.jit(jax.vmap(hfield_contact.prism_contact, in_axes=(0, None, 0, 0, 0)))(
            jnp.asarray(tops), -0.1, jnp.asarray(a), jnp.asarray(b), jnp.asarray(radius))[0]
        bound = jax.jit(jax.vmap(lambda a_, b_, r_, lo_, zt: hfield_contact._bound(a_, b_, r_, lo_[None],
                                                                                   jnp.asarray(cell), zt[None])[0]))(
            jnp.asarray(a), jnp.asarray(b), jnp.asarray(radius), jnp.asarray(lo), jnp.asarray(tops[:, :, 2].max(1)))
    dist, bound = np.asarray(dist), np.asarray(bound)
    touch = dist < 0
    assert touch.sum() > 1000 and (~touch).sum() > 1000, touch.sum()
    assert np.all(bound[touch] < hfield_contact.BOUND_SLACK), (bound[touch].max(), dist[touch][bound[touch].argmax()])
    assert np.mean(bound[~touch] >= hfield_contact.BOUND_SLACK) > 0.5, np.mean(bound[~touch] >= 0)


def _group(rng, mx, num, deep_every=3):
    """`num` capsules at random poses over the field of `mx` (from `_model`), as `hfield_group` takes them."""
    hinfo = mesh.hfield(mx, 0)
    hpos = np.array([0.05, -0.03, 0.2])
    hmat = np.zeros(9)
    mujoco.mju_euler2Quat(q := np.zeros(4), np.deg2rad([4, -3, 30]), "xyz")
    mujoco.mju_quat2Mat(hmat, q)
    hmat = hmat.reshape(3, 3)
    data = np.asarray(hinfo.data)
    pos, mat = np.zeros((num, 3)), np.zeros((num, 3, 3))
    radius, half = rng.uniform(0.02, 0.06, num), rng.uniform(0.05, 0.2, num)
    for i in range(num):
        qq = rng.normal(size=4)
        qq /= np.linalg.norm(qq)
        m9 = np.zeros(9)
        mujoco.mju_quat2Mat(m9, qq)
        mat[i] = m9.reshape(3, 3)
        axis = hmat.T @ mat[i][:, 2]
        xy = rng.uniform(-0.25, 0.25, 2)
        c, r = ((xy + SIZE) / (2 * SIZE) * (N - 1)).astype(int)
        top = data[c:c + 2, r:r + 2].max() * ZS
        z = top + radius[i] + half[i] * abs(axis[2]) - rng.uniform(0.0, 0.05 if i % deep_every else 0.12)
        pos[i] = hmat @ np.array([xy[0], xy[1], z]) + hpos
    h = hinfo.replace(pos=jnp.asarray(np.repeat(hpos[None], num, 0)), mat=jnp.asarray(np.repeat(hmat[None], num, 0)))
    return h, jnp.asarray(pos), jnp.asarray(mat), jnp.asarray(radius), jnp.asarray(half)


def test_group_equals_every_prism():
    """`hfield_group` (a group of pairs, the exact test only on the prisms of lowest bound) gives every pair the
    contacts `hfield_geom` (every prism) gives it, in the same slots, when no candidate is dropped; with too few
    candidates it keeps a subset of them, each in its pair, never more than it tested."""
    rng = np.random.default_rng(2)
    ncon, subgrid = 24, (7, 7)
    mm = _model((0.06, 0.2), 0.05)
    mm.hfield_data[:] = rng.uniform(0.4, 0.6, N * N)      # gentle: capsules lying on it touch many prisms
    with jax.enable_x64(True):
        mx = mjx.put_model(mm, impl="jax")
        h, pos, mat, radius, half = _group(rng, mx, 12)
        one = lambda hp, hm, p_, m_, r_, hl: hfield_contact.hfield_geom(   # noqa: E731
            h.replace(pos=hp, mat=hm), p_, m_, r_, hl, subgrid, ncon)
        full = [np.asarray(x).reshape(12 * ncon, *x.shape[2:])     # jitted: one program, not op by op
                for x in jax.jit(jax.vmap(one))(h.pos, h.mat, pos, mat, radius, half)]
        counts = np.asarray(hfield_contact.candidate_counts(h, pos, mat, radius, half, subgrid))
        n_full = int((full[0] < 1.0).sum())
        assert n_full > 15 and counts.sum() >= n_full, (n_full, counts)
        group_of = jax.jit(hfield_contact.hfield_group, static_argnums=(5, 6, 7))
        group = [np.asarray(x) for x in group_of(h, pos, mat, radius, half, subgrid, ncon, int(counts.sum()))]
        few = [np.asarray(x) for x in group_of(h, pos, mat, radius, half, subgrid, ncon, 12)]
    act = full[0] < 1.0
    np.testing.assert_array_equal(group[0] < 1.0, act)
    for g, f in zip(group, full):
        np.testing.assert_allclose(g[act], f[act], atol=1e-12)
    kept = few[0] < 1.0
    assert 0 < kept.sum() <= 12
    for row in np.nonzero(kept)[0]:            # each kept contact is one of the full set's, in its own pair
        pair = slice(row // ncon * ncon, (row // ncon + 1) * ncon)
        j = np.argmin(np.abs(full[0][pair] - few[0][row]) + np.abs(full[1][pair] - few[1][row]).sum(-1))
        assert abs(full[0][pair][j] - few[0][row]) < 1e-12 and np.allclose(full[1][pair][j], few[1][row])
