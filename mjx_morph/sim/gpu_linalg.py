"""One fused Pallas kernel per Cholesky factorisation and one per solve, for MJX on a GPU (`env.linalg=pallas`).

Why: a GPU profile of the 64-env rollout (Newton solver, padded robots of nv ~58) spent ~46% of the GPU time in
cuSOLVER's batched Cholesky (about 50 small kernels per factorisation, 72 us a call, 3,115 factorisations per
80-step rollout) and cuBLAS's trsm for the solves (30 us a call, 6,230 calls). MJX factors and solves with
`jax.scipy.linalg.cho_factor` / `cho_solve` (the Newton Hessian in solver.py, the mass matrix in smooth.py's
factor_m / solve_m, the implicit integrator in forward.py); these matrices are small, so the time is launches and
their latency, not arithmetic.

What: `cho_factor(a, lower=False, ...)` and `cho_solve((c, lower), b, ...)` with the signatures, returns and
semantics of `jax.scipy.linalg`'s: the factor reads one triangle of `a` (the upper one for lower=False, as JAX) and
returns the factor with zeros in the other triangle; a matrix that is not positive definite (a pivot <= 0 or NaN)
gives NaN in the whole factor triangle (JAX: the same for a pivot <= 0); the solve reads only the factor's
triangle; `b` is a vector (n,) or a matrix (..., n, k), with the leading batch dimensions of `c` and `b` broadcast,
and a batch of vectors (..., n) where `c` has one more dimension (JAX's deprecated reading, kept). Each kernel is
written for one matrix held whole by one program (a 64 x 64 float32 tile lives in the registers of 4 warps):
    factor   right-looking, one column a step (`fori_loop` over the columns): the column is picked out of the
             tile by a masked row sum, scaled by the pivot's square root, and the trailing block takes the rank-1
             update, masked to the rows and columns after the pivot;
    solve    forward substitution with L, then back substitution with L^T, in the same kernel, each a column of
             the factor a step, picked out by a masked sum (Triton cannot index a register tile by a traced index).
Triton needs power-of-two shapes: n is padded up to the next power of two (identity on the padded diagonal, zeros
elsewhere; k likewise with zero columns) and the result sliced back (the 100 train robots' nv of 58 runs as 64; an nv
just above a power of two costs more: the generated robots' 70 runs as 128, a 4x larger tile). A batch (MJX runs
vmapped over the envs) is `pallas_call`'s batching rule: one program per matrix, the batch as the launch grid.
float32 only (MJX's physics); other dtypes, and n > MAX_N (a tile too large for one program's registers), go to
env.linalg=jax's functions (`cpu_linalg.default_functions`). Not differentiable (the physics is never
differentiated); jit and vmap work.

Where it runs: with the default backend a CPU (seen while tracing), `pallas_call(interpret=True)` runs the same
kernels as plain JAX, which is how the tests check them; on a GPU they lower through Pallas' Triton backend
(`CompilerParams` of jax.experimental.pallas.triton, so that Pallas does not pick Mosaic GPU). `interpret=` forces
either (tests lower for CUDA on a CPU to check that the kernels lower to Triton IR).

How it is switched: `EnvConfig.linalg` ("jax": JAX's functions, the default; "pallas": these), which MJX sees
through `linalg.py`'s view while an env traces its physics. Not yet measured on a GPU: whether it is faster than
cuSOLVER / cuBLAS there (`experiments/bench_cholesky.py` times the kernels alone, `experiments.bench_train
mode=rollout env.linalg=pallas` the rollout), and the Triton compilation itself (TTIR to PTX) never ran here.
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl

from . import cpu_linalg

try:
    from jax.experimental.pallas.triton import CompilerParams as _TritonParams
except ImportError:                                     # older JAX spelled it TritonCompilerParams
    from jax.experimental.pallas import TritonCompilerParams as _TritonParams  # type: ignore[attr-defined,no-redef]

#: the largest n factored here (padded to 128: a 64 KiB tile for one program); larger go to env.linalg=jax's
MAX_N = 128



def padded_size(n: int) -> int:
    """The power of two the kernels pad n up to."""
    return 1 if n <= 1 else 1 << (n - 1).bit_length()


def _interpret(interpret: bool | None) -> bool:
    return jax.default_backend() == "cpu" if interpret is None else bool(interpret)


def num_warps_for(size: int) -> int:
    """Warps of one program for a `size` x `size` tile: ~32 values of the matrix per thread, 1-8 (64 x 64: 4). A
    guess until measured (`experiments.bench_cholesky warps=[1,2,4,8]` times the others)."""
    return min(8, max(1, size * size // 1024))


def _params(size: int, num_warps: int | None):
    return _TritonParams(num_warps=num_warps_for(size) if num_warps is None else int(num_warps), num_stages=1)


def _float(x: jax.Array) -> jax.Array:
    """`x` as an inexact array (integers and booleans to float32, as JAX's promotion without x64)."""
    return x if jnp.issubdtype(x.dtype, jnp.inexact) else x.astype(jnp.float32)


# ---- kernels (one matrix each) ---------------------------------------------------------------------------------
def _factor_kernel(a_ref, l_ref):
    """L (zeros above the diagonal) of the lower triangle of the tile; NaN in L's triangle if a pivot is not > 0."""
    n = a_ref.shape[0]
    r = jax.lax.broadcasted_iota(jnp.int32, (n,), 0)
    cols = jax.lax.broadcasted_iota(jnp.int32, (n, n), 1)

    def column(j, carry):
        a, ok = carry                       # a: columns < j hold L's, the block from (j, j) on is still to factor
        col = jnp.sum(jnp.where(cols == j, a, 0.0), axis=1)            # a[:, j]
        d = jnp.sum(jnp.where(r == j, col, 0.0))                        # the pivot a[j, j]
        ok = jnp.where(d > 0.0, ok, 0.0)                                # False for NaN too
        l = jnp.where(r >= j, col / jnp.sqrt(d), 0.0)                   # L[:, j]
        below = jnp.where(r > j, l, 0.0)
        a = jnp.where(cols == j, l[:, None], a - below[:, None] * below[None, :])
        return a, ok

    a, ok = jax.lax.fori_loop(0, n, column, (a_ref[...], jnp.float32(1.0)))
    rows = jax.lax.broadcasted_iota(jnp.int32, (n, n), 0)
    l_ref[...] = jnp.where((ok > 0.0) | (rows < cols), a, jnp.nan)


def _solve_kernel(c_ref, b_ref, x_ref, *, lower: bool):
    """x with L L^T x = b, L = the tile's lower triangle (lower) or the transpose of its upper triangle."""
    c = c_ref[...]
    n, k = b_ref.shape
    r = jax.lax.broadcasted_iota(jnp.int32, (n,), 0)
    rb = jax.lax.broadcasted_iota(jnp.int32, (n, k), 0)
    rows = jax.lax.broadcasted_iota(jnp.int32, (n, n), 0)
    cols = jax.lax.broadcasted_iota(jnp.int32, (n, n), 1)

    def pick_col(j):                        # c[:, j]
        return jnp.sum(jnp.where(cols == j, c, 0.0), axis=1)

    def pick_row(j):                        # c[j, :]
        return jnp.sum(jnp.where(rows == j, c, 0.0), axis=0)

    def substitute(j, y, line, keep):
        """Fix unknown j of y from `line` (the factor's entries against unknown j) and eliminate it from the rows
        `keep` selects."""
        yj = jnp.sum(jnp.where(rb == j, y, 0.0), axis=0) / jnp.sum(jnp.where(r == j, line, 0.0))     # (k,)
        rest = jnp.where(keep, line, 0.0)
        return jnp.where(rb == j, yj[None, :], y - rest[:, None] * yj[None, :])

    def forward(j, y):                      # L z = b: column j of L
        return substitute(j, y, pick_col(j) if lower else pick_row(j), r > j)

    def backward(i, y):                     # L^T x = z, the last unknown first: column j of L^T = row j of L
        j = n - 1 - i
        return substitute(j, y, pick_row(j) if lower else pick_col(j), r < j)

    y = jax.lax.fori_loop(0, n, forward, b_ref[...])
    x_ref[...] = jax.lax.fori_loop(0, n, backward, y)


# ---- one matrix: pad, call, slice ---------------------------------------------------------------------------------
def _pad_square(a: jax.Array, size: int) -> jax.Array:
    n = a.shape[-1]
    if n == size:
        return a
    i = jnp.arange(size)
    eye = (i[:, None] == i[None, :]) & (i[:, None] >= n)
    return jnp.where(eye, jnp.ones((), a.dtype), jnp.pad(a, ((0, size - n), (0, size - n))))


def _factor_one(a: jax.Array, interpret: bool, num_warps: int | None) -> jax.Array:
    """L of the lower triangle of one (n, n) matrix."""
    n = a.shape[-1]
    size = padded_size(n)
    out = pl.pallas_call(_factor_kernel, out_shape=jax.ShapeDtypeStruct((size, size), a.dtype),
                         interpret=interpret, compiler_params=_params(size, num_warps), name="mjx_morph_cho_factor")(
        _pad_square(a, size))
    return out[:n, :n]


def _solve_one(c: jax.Array, b: jax.Array, lower: bool, interpret: bool, num_warps: int | None) -> jax.Array:
    """x of one (n, n) factor and one (n, k) right-hand side."""
    n, k = b.shape
    size, width = padded_size(n), padded_size(k)
    b = jnp.pad(b, ((0, size - n), (0, width - k)))
    kernel = lambda c_ref, b_ref, x_ref: _solve_kernel(c_ref, b_ref, x_ref, lower=lower)  # noqa: E731
    out = pl.pallas_call(kernel, out_shape=jax.ShapeDtypeStruct((size, width), b.dtype), interpret=interpret,
                         compiler_params=_params(size, num_warps), name="mjx_morph_cho_solve")(_pad_square(c, size), b)
    return out[:n, :k]


def _over_batch(fn, batch: tuple[int, ...], *args: jax.Array) -> jax.Array:
    """`fn` of single matrices applied over the leading `batch` dimensions of `args` (one vmap of the flattened
    batch: pallas_call's batching rule makes it the launch grid)."""
    if not batch:
        return fn(*args)
    size = math.prod(batch)
    flat = [x.reshape((size, *x.shape[len(batch):])) for x in args]
    out = jax.vmap(fn)(*flat)
    return out.reshape((*batch, *out.shape[1:]))


def _kernel_ok(x: jax.Array) -> bool:
    return x.dtype == jnp.float32 and x.shape[-1] <= MAX_N


# ---- the public functions: jax.scipy.linalg's signatures ----------------------------------------------------------
def cho_factor(a, lower: bool = False, overwrite_a: bool = False, check_finite: bool = True, *,
               interpret: bool | None = None, num_warps: int | None = None):
    """`jax.scipy.linalg.cho_factor` as one Pallas kernel per matrix: (c, lower), c of shape (..., n, n).
    `interpret`: None (the default backend a CPU), True or False; `num_warps`: a program's warps on a GPU (None:
    `num_warps_for`). overwrite_a and check_finite are ignored, as by JAX."""
    a = _float(jnp.asarray(a))
    if a.ndim < 2 or a.shape[-1] != a.shape[-2]:
        raise ValueError(f"cho_factor: expected a square matrix (..., n, n), got shape {a.shape}")
    if not _kernel_ok(a) or a.shape[-1] == 0:
        return cpu_linalg.default_functions()[0](a, lower=lower, overwrite_a=overwrite_a, check_finite=check_finite)
    tri = a if lower else jnp.swapaxes(a, -1, -2)          # the triangle JAX reads, as a lower one
    interp = _interpret(interpret)
    l = _over_batch(lambda x: _factor_one(x, interp, num_warps), a.shape[:-2], tri)
    return (l if lower else jnp.swapaxes(l, -1, -2)), lower


def cho_solve(c_and_lower, b, overwrite_b: bool = False, check_finite: bool = True, *,
              interpret: bool | None = None, num_warps: int | None = None):
    """`jax.scipy.linalg.cho_solve` as one Pallas kernel per right-hand side matrix (forward and back
    substitution in one kernel). `interpret`, `num_warps` as for `cho_factor`."""
    c, lower = c_and_lower
    c, b = _float(jnp.asarray(c)), _float(jnp.asarray(b))
    if c.ndim < 2 or c.shape[-1] != c.shape[-2]:
        raise ValueError(f"cho_solve: expected a square factor (..., n, n), got shape {c.shape}")
    n = c.shape[-1]
    if not _kernel_ok(c) or b.dtype != c.dtype or n == 0:
        return cpu_linalg.default_functions()[1]((c, lower), b, overwrite_b=overwrite_b, check_finite=check_finite)
    vector = b.ndim == 1 or (c.ndim == b.ndim + 1 and b.shape[-1] == n)   # (n,), or JAX's batched vectors
    rhs = b[..., None] if vector else b
    if rhs.ndim < 2 or rhs.shape[-2] != n:
        raise ValueError(f"cho_solve: right-hand side of shape {b.shape} does not fit a factor of shape {c.shape}")
    batch = jnp.broadcast_shapes(c.shape[:-2], rhs.shape[:-2])
    c = jnp.broadcast_to(c, (*batch, n, n))
    rhs = jnp.broadcast_to(rhs, (*batch, *rhs.shape[-2:]))
    interp = _interpret(interpret)
    x = _over_batch(lambda cc, bb: _solve_one(cc, bb, bool(lower), interp, num_warps), batch, c, rhs)
    return x[..., 0] if vector else x
