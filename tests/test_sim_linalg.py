"""MJX's Cholesky choice (`env.linalg`, mjx_morph/sim/linalg.py) and the fused Pallas kernels (sim/gpu_linalg.py).

On this CPU the kernels run in Pallas' interpret mode (the same kernel code as plain JAX); that they lower to Triton
is checked by lowering them for CUDA here (Triton IR, verified; the compilation to PTX needs a GPU):
- factor and solve match jax.scipy.linalg within FACTOR_TOL / SOLVE_TOL of the result's largest entry (float32) for
  random SPD matrices of n in {1, 5, 17, 58, 64}, lower and upper, vector and matrix b, under jit, under vmap and
  with an explicit batch;
- JAX's semantics at the edges: a matrix that is not positive definite gives NaN in the factor's triangle, the
  solve reads only the factor's triangle, batch broadcasting, integer inputs; n > MAX_N goes to JAX's functions;
- the key: an unknown value is refused, Hydra composes it for runs and bench_train, a resume may change it;
- one MJX step (contacts, Newton solver, mass-matrix factor and solve) of two envs of one small robot built with
  env.linalg=pallas matches the default's, both built in one process, each tracing its own choice.
"""
from __future__ import annotations

from unittest import mock

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml

from mjx_morph.run import FAST_COMPILE
from mjx_morph.sim import cpu_linalg, gpu_linalg, linalg

#: largest difference from jax.scipy.linalg allowed, relative to the largest entry of JAX's result (measured: < 1e-6)
FACTOR_TOL = 1e-5
SOLVE_TOL = 1e-4
SIZES = (1, 5, 17, 58, 64)


def _spd(rng, batch, n):
    m = rng.normal(size=(batch, n, n)).astype(np.float32)
    return m @ m.transpose(0, 2, 1) / n + np.eye(n, dtype=np.float32)


def _both(factor, solve, a, b, bm):
    out = []
    for lower in (False, True):
        c = factor(a, lower=lower)
        assert c[1] is lower
        out += [c[0], solve(c, b), solve(c, bm)]
    return out


def _close(got, want, tol, what):
    got, want = np.asarray(got), np.asarray(want)
    assert got.shape == want.shape, what
    err = np.max(np.abs(got - want)) / max(np.max(np.abs(want)), 1e-30)
    assert err < tol, (what, err)


@pytest.mark.parametrize("n", SIZES)
def test_factor_and_solve_match_jax(n):
    rng = np.random.default_rng(n)
    a, b, bm = _spd(rng, 3, n), rng.normal(size=(3, n)).astype(np.float32), rng.normal(size=(3, n, 3)).astype(
        np.float32)
    ours = lambda *x: _both(gpu_linalg.cho_factor, gpu_linalg.cho_solve, *x)                        # noqa: E731
    jaxs = lambda *x: _both(jax.scipy.linalg.cho_factor, jax.scipy.linalg.cho_solve, *x)             # noqa: E731

    def all_ways(a, b, bm):     # one program: unbatched (jit), vmapped, explicit batch; ours and JAX's
        explicit = gpu_linalg.cho_factor(a)
        return (ours(a[0], b[0], bm[0]), jax.vmap(ours)(a, b, bm), [explicit[0], gpu_linalg.cho_solve(explicit, bm)],
                jaxs(a[0], b[0], bm[0]), jax.vmap(jaxs)(a, b, bm))
    one, vmapped, explicit, want_one, want_vmapped = jax.jit(all_ways)(a, b, bm)
    for got, want in ((one, want_one), (vmapped, want_vmapped), (explicit, [want_vmapped[0], want_vmapped[2]])):
        for i, (g, w) in enumerate(zip(got, want)):
            _close(g, w, FACTOR_TOL if i % 3 == 0 else SOLVE_TOL, (n, i))
    # the factor is a Cholesky factor of a, zeros in the other triangle, as JAX's
    u = np.asarray(one[0])
    np.testing.assert_array_equal(np.tril(u, -1), 0)
    np.testing.assert_allclose(u.T @ u, a[0], atol=FACTOR_TOL * np.abs(a[0]).max() * 4)


def test_jax_semantics_at_the_edges():
    rng = np.random.default_rng(1)
    n = 6
    a = _spd(rng, 4, n)
    bad = a.copy()
    bad[1, 2, 2] = -50.0                                      # not positive definite
    b = rng.normal(size=(4, n)).astype(np.float32)
    messy = np.asarray(jax.scipy.linalg.cho_factor(a)[0]) + np.tril(rng.normal(size=(n, n)), -1).astype(np.float32)

    def f(a, bad, b, messy, ints):
        return (gpu_linalg.cho_factor(bad)[0], jax.scipy.linalg.cho_factor(bad)[0],
                gpu_linalg.cho_solve((messy, False), b),                                  # batched vectors
                jax.scipy.linalg.cho_solve((messy, False), b[..., None])[..., 0],
                gpu_linalg.cho_solve(gpu_linalg.cho_factor(a), b[0]),                 # one b for every matrix
                gpu_linalg.cho_factor(ints)[0])
    got_bad, want_bad, got_messy, want_messy, shared, from_ints = (np.asarray(x) for x in jax.jit(f)(
        a, bad, b, messy, 3 * np.eye(n, dtype=int)))
    np.testing.assert_array_equal(np.isnan(got_bad), np.isnan(want_bad))     # NaN in the triangle of matrix 1 only
    assert np.isnan(got_bad[1]).sum() == n * (n + 1) // 2 and not np.isnan(got_bad[[0, 2, 3]]).any()
    np.testing.assert_array_equal(got_bad[1][np.tril_indices(n, -1)], 0)
    _close(got_messy, want_messy, SOLVE_TOL, "only the factor's triangle is read")
    _close(shared, np.linalg.solve(a, np.broadcast_to(b[0], (4, n))[..., None])[..., 0], SOLVE_TOL, "broadcast b")
    assert from_ints.dtype == np.float32
    np.testing.assert_allclose(from_ints, np.sqrt(3) * np.eye(n), rtol=1e-6)
    big = jax.ShapeDtypeStruct((gpu_linalg.MAX_N + 1,) * 2, jnp.float32)         # beyond one program's tile
    fallback = str(jax.make_jaxpr(gpu_linalg.cho_factor)(big))
    assert "pallas_call" not in fallback
    assert ("cholesky" in fallback) != cpu_linalg.applies()      # env.linalg=jax's: the CPU loops where they apply
    assert "pallas_call" in str(jax.make_jaxpr(gpu_linalg.cho_factor)(jax.ShapeDtypeStruct((58, 58), jnp.float32)))


def _triton_kernels(fn, *args):
    """The Triton IR modules (verified) and launches (grid x, grid y, warps) of `fn` lowered for CUDA (jaxlib <=
    0.10.2 keeps the IR in the custom call; later jaxlibs compile it while lowering, which needs a GPU)."""
    from jax._src.lib import version as jaxlib_version
    if jaxlib_version > (0, 10, 2):
        pytest.skip(f"jaxlib {jaxlib_version} compiles Triton kernels while lowering: needs a GPU")
    from jax._src.lib.mlir import ir
    from jax._src.pallas.triton import lowering as triton_lowering
    hlo = jax.jit(fn).trace(*args).lower(lowering_platforms=("cuda",)).compiler_ir("stablehlo")
    found = []

    def walk(op):
        for region in op.regions:
            for block in region.blocks:
                for inner in block.operations:
                    attrs = inner.operation.attributes
                    if inner.operation.name == "stablehlo.custom_call" and "triton" in str(attrs["call_target_name"]):
                        config = ir.DictAttr(attrs["mhlo.backend_config"])
                        launch = tuple(ir.IntegerAttr(config[k]).value for k in ("grid_x", "grid_y", "num_warps"))
                        found.append((ir.StringAttr(config["ir"]).value_bytes, launch))
                    walk(inner.operation)
    walk(hlo.operation)
    out = []
    for code, grid in found:
        with triton_lowering._new_ir_context():
            module = ir.Module.parse(code)
            assert module.operation.verify()
            out.append((str(module), grid))
    return out


def test_kernels_lower_to_triton_ir():
    s = jax.ShapeDtypeStruct

    def f(a, b, bm):                                          # what MJX calls (upper, vector b) and the rest
        return _both(lambda x, lower: gpu_linalg.cho_factor(x, lower=lower, interpret=False),
                     lambda c, y: gpu_linalg.cho_solve(c, y, interpret=False), a, b, bm)
    one = _triton_kernels(f, s((58, 58), jnp.float32), s((58,), jnp.float32), s((58, 3), jnp.float32))
    factors, solves = one[0::3], one[1::3] + one[2::3]       # per triangle: factor, vector solve, matrix solve
    assert len(one) == 6 and all("scf.for" in text for text, _ in one)
    # the factor holds the 64 x 64 tile in 4 warps; a solve reads rows of the factor into one warp
    assert all(launch == (1, 1, 4) and "tensor<64x64xf32>" in text for text, launch in factors)
    assert all(launch == (1, 1, 1) and "tensor<1x64xf32>" in text and "tensor<64x64xf32>" not in text
               for text, launch in solves)
    envs = _triton_kernels(jax.vmap(jax.vmap(f)), s((2, 64, 58, 58), jnp.float32), s((2, 64, 58), jnp.float32),
                           s((2, 64, 58, 3), jnp.float32))
    assert len(envs) == 6 and all(launch[:2] == (64, 2) for _, launch in envs)     # one program per matrix
    two = _triton_kernels(lambda a: gpu_linalg.cho_factor(a, interpret=False, num_warps=2)[0],
                          s((5, 5), jnp.float32))
    assert [launch for _, launch in two] == [(1, 1, 2)] and "tensor<8x8xf32>" in two[0][0]


def test_the_key_is_checked_composed_and_free_on_resume(tmp_path):
    from experiments.bench_train import BenchTrainConfig
    from mjx_morph.run import RunDir, compose, compose_run_config
    from mjx_morph.run.config import FREE, IDENTITY, to_dict
    from mjx_morph.sim.env import make_env
    with pytest.raises(ValueError, match="env.linalg='cusolver': expected one of auto, jax, pallas"):
        make_env("gen/train", "ft", linalg="cusolver")
    from mjx_morph.sim import fidelity
    with pytest.raises(ValueError, match="env.linalg='cusolver'"):     # check_sim's path: refused before any work
        fidelity.compare([], linalg="cusolver")
    assert linalg.current() == "auto" and linalg.functions("pallas")[0] is gpu_linalg.cho_factor
    with linalg.use("pallas"):
        assert linalg.current() == "pallas"
    # auto: the kernels where the default backend is a GPU, JAX's functions (here the CPU's) elsewhere
    assert linalg.resolve("auto") == "jax" and linalg.functions("auto") == linalg.functions("jax")
    with mock.patch.object(jax, "default_backend", lambda: "gpu"):
        assert linalg.resolve("auto") == "pallas" and linalg.resolve("jax") == "jax"
        assert linalg.functions()[1] is gpu_linalg.cho_solve          # outside any block: auto
    assert compose_run_config(["env.linalg=pallas"]).env.linalg == "pallas"
    assert compose_run_config([]).env.linalg == "auto"
    bench = compose("bench_train", ["mode=rollout", "env.linalg=pallas", "ppo.num_envs=64"], BenchTrainConfig)
    assert bench.env.linalg == "pallas"
    saved = to_dict(compose_run_config([f"run_dir={tmp_path}"]))
    del saved["env"]["linalg"]                                # a run from before the key
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(saved, sort_keys=False))
    for value in ("auto", "jax", "pallas"):
        RunDir(tmp_path, to_dict(compose_run_config([f"run_dir={tmp_path}", f"env.linalg={value}"])), IDENTITY, FREE)


def test_mjx_step_with_pallas_matches_jax():
    """One MJX step of 2 envs of the smallest shipped robot (contacts with the floor: Newton solver), with each
    setting; both envs live in one process and trace their own Cholesky."""
    from mujoco import mjx

    from mjx_morph.sim.env import make_env
    from sim_reference import available_robots
    robot = min(available_robots(), key=lambda m: m.num_limbs)
    envs = {k: make_env([robot], "ft", self_collision=False, substeps=1, linalg=k).env for k in ("jax", "pallas")}
    m = envs["jax"].sm.model_for(0)
    rng = np.random.default_rng(0)
    real_q, real_v = np.asarray(envs["jax"].tables.real_qpos[0]), np.asarray(envs["jax"].tables.real_dof[0])
    qpos = jnp.asarray(np.asarray(m.qpos0) + 0.05 * rng.normal(size=(2, m.nq)) * real_q, jnp.float32)
    qvel = jnp.asarray(rng.normal(size=(2, m.nv)) * real_v, jnp.float32)
    out = {}
    for k, env in envs.items():
        with env.physics():
            d0 = mjx.make_data(m, impl="jax")

        def step(qp, qv, env=env, d0=d0):
            with env.physics():
                d = mjx.step(m, d0.replace(qpos=qp, qvel=qv))
            return d.qpos, d.qvel, d.qacc, d.qfrc_constraint
        traced = jax.jit(jax.vmap(step), compiler_options=FAST_COMPILE).trace(qpos, qvel)
        assert ("pallas_call" in str(traced.jaxpr)) == (k == "pallas"), k
        out[k] = traced.lower().compile()(qpos, qvel)
    assert np.abs(np.asarray(out["jax"][3])).max() > 1.0          # the floor pushes: the solver had work
    for name, got, want in zip(("qpos", "qvel", "qacc", "qfrc_constraint"), out["pallas"], out["jax"]):
        _close(got, want, SOLVE_TOL, name)


def test_bench_cholesky_prints_a_row_per_case_and_the_kernels_agree(capsys):
    """experiments.bench_cholesky on a CPU (the kernels interpreted): the header, one row per implementation and
    batch with three positive times, and pallas' solution within float32 rounding of JAX's."""
    from experiments import bench_cholesky
    assert bench_cholesky.main(["n=5", "batches=[3]", "reps=2"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("# jax ") and "n=5" in lines[0]
    rows = [line.split() for line in lines[2:]]
    assert [r[:2] for r in rows] == [["3", "jax"], ["3", "pallas"]], lines
    assert all(float(t) > 0 for r in rows for t in r[2:5])
    assert float(rows[1][5]) < 1e-5
