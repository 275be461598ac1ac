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
and a batch of vectors (..., n) where `c` has one more dimension (JAX's deprecated reading, kept). One program a
matrix:
    factor   right-looking, one column a step (`fori_loop` over the columns), the matrix held whole as a register
             tile (64 x 64 float32 in 4 warps): the column is picked out of the tile by a masked row sum (Triton
             cannot index a register tile by a traced index), scaled by the pivot's square root, and the trailing
             block takes the rank-1 update, masked to the rows and columns after the pivot;
    solve    forward substitution with L, then back substitution with L^T, in the same kernel, one unknown a step
             from one row of L (forward) or of L^T (back; XLA transposes the factor outside, and for MJX's upper
             factor that transpose cancels the factor's own) read from memory, against the unknowns found so far:
             one reduction a step in one warp, no tile of the factor held (session 61: the first version picked
             columns out of a register tile, three reductions a step across 4 warps, and took twice the factor's
             time in the GPU profile).
Triton needs power-of-two shapes: n is padded up to the next power of two with zeros (k likewise), the loops stop at
n, and the result is sliced back (the 100 train robots' nv of 58 runs as 64; an nv just above a power of two costs
more: the generated robots' 70 runs as 128, a 4x larger tile). A batch (MJX runs
vmapped over the envs) is `pallas_call`'s batching rule: one program per matrix, the batch as the launch grid.
float32 only (MJX's physics); other dtypes, and n > MAX_N (a tile too large for one program's registers), go to
env.linalg=jax's functions (`cpu_linalg.default_functions`). Not differentiable (the physics is never
differentiated); jit and vmap work.

Where it runs: with the default backend a CPU (seen while tracing), `pallas_call(interpret=True)` runs the same
kernels as plain JAX, which is how the tests check them; on a GPU they lower through Pallas' Triton backend
(`CompilerParams` of jax.experimental.pallas.triton, so that Pallas does not pick Mosaic GPU). `interpret=` forces
either (tests lower for CUDA on a CPU to check that the kernels lower to Triton IR).

How it is switched: `EnvConfig.linalg` ("auto", the default: these on a GPU, JAX's functions elsewhere; "jax":
JAX's functions; "pallas": these), which MJX sees through `linalg.py`'s view while an env traces its physics;
linalg.py's docstring says what was measured on a GPU and why these are its default. Session 61 also measured the
first version's kernels (agreeing with cuSOLVER's to 6e-7; the 64-env rollout +10%, the 1,024-env one -17%), which
this solve replaced. `experiments/bench_cholesky.py` times the kernels alone, `experiments.bench_train
mode=rollout env.linalg=pallas` the rollout.
"""
from __future__ import annotations

import functools
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
#: warps of one solve program: its tiles are rows of (k, size), so one warp holds them and its reductions stay in
#: the warp (no shared memory and barrier a step)
SOLVE_WARPS = 1



def padded_size(n: int) -> int:
    """The power of two the kernels pad n up to."""
    return 1 if n <= 1 else 1 << (n - 1).bit_length()


def _interpret(interpret: bool | None) -> bool:
    return jax.default_backend() == "cpu" if interpret is None else bool(interpret)


def num_warps_for(size: int) -> int:
    """Warps of one program for a `size` x `size` tile: ~32 values of the matrix per thread, 1-8 (64 x 64: 4). A
    guess until measured (`experiments.bench_cholesky warps=[1,2,4,8]` times the others)."""
    return min(8, max(1, size * size // 1024))


def _params(num_warps: int):
    return _TritonParams(num_warps=int(num_warps), num_stages=1)


def _float(x: jax.Array) -> jax.Array:
    """`x` as an inexact array (integers and booleans to float32, as JAX's promotion without x64)."""
    return x if jnp.issubdtype(x.dtype, jnp.inexact) else x.astype(jnp.float32)


# ---- kernels (one matrix each) ---------------------------------------------------------------------------------
def _factor_kernel(a_ref, l_ref, *, n: int):
    """L (zeros above the diagonal) of the lower triangle of the tile's first n rows and columns (the rest is zero
    padding, left as it is); NaN in L's triangle if a pivot is not > 0."""
    size = a_ref.shape[0]
    r = jax.lax.broadcasted_iota(jnp.int32, (size,), 0)
    cols = jax.lax.broadcasted_iota(jnp.int32, (size, size), 1)

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
    rows = jax.lax.broadcasted_iota(jnp.int32, (size, size), 0)
    l_ref[...] = jnp.where((ok > 0.0) | (rows < cols), a, jnp.nan)


def _solve_kernel(l_ref, lt_ref, bt_ref, xt_ref, *, n: int):
    """x^T with L L^T x = b, from L (`l_ref`), L^T (`lt_ref`) and b^T (`bt_ref`, one right-hand side a row).

    Both substitutions go row by row, reading one row of L (forward) or of L^T (back) from memory a step, so no
    tile of the factor is held and each step has one reduction on its critical path (the row against the unknowns
    found so far, the new right-hand side entry folded in), along the rows of the (k, size) tile of unknowns."""
    k, size = bt_ref.shape
    cols = jax.lax.broadcasted_iota(jnp.int32, (k, size), 1)
    line = jax.lax.broadcasted_iota(jnp.int32, (1, size), 1)

    def substitute(ref, j, v, done):
        """Fix unknown j of v (k, size): (v[:, j] - row . v over the columns `done` selects) / row[j], with `row`
        row j of `ref`."""
        row = ref[pl.ds(j, 1), :]                                                          # (1, size)
        t = jnp.sum(jnp.where(done, -row * v, jnp.where(cols == j, v, 0.0)), axis=1, keepdims=True)   # (k, 1)
        pivot = jnp.sum(jnp.where(line == j, row, 0.0), axis=1, keepdims=True)                   # (1, 1)
        return jnp.where(cols == j, t / pivot, v)

    def forward(j, v):                      # L z = b: z_j from row j of L and z_0..z_{j-1}
        return substitute(l_ref, j, v, cols < j)

    def backward(i, v):                     # L^T x = z, the last unknown first, from row j of L^T
        j = n - 1 - i
        return substitute(lt_ref, j, v, cols > j)

    v = jax.lax.fori_loop(0, n, forward, bt_ref[...])
    xt_ref[...] = jax.lax.fori_loop(0, n, backward, v)


# ---- one matrix: pad, call, slice ---------------------------------------------------------------------------------
def _pad(x: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """`x` with zeros after its entries up to `shape` (the kernels never read the padding's values: their loops
    stop at the true size)."""
    return jnp.pad(x, [(0, s - d) for s, d in zip(shape, x.shape)])


def _factor_one(a: jax.Array, interpret: bool, num_warps: int | None) -> jax.Array:
    """L of the lower triangle of one (n, n) matrix."""
    n = a.shape[-1]
    size = padded_size(n)
    kernel = functools.partial(_factor_kernel, n=n)
    out = pl.pallas_call(kernel, out_shape=jax.ShapeDtypeStruct((size, size), a.dtype), interpret=interpret,
                         compiler_params=_params(num_warps_for(size) if num_warps is None else num_warps),
                         name="mjx_morph_cho_factor")(_pad(a, (size, size)))
    return out[:n, :n]


def _solve_one(l: jax.Array, b: jax.Array, interpret: bool, num_warps: int | None) -> jax.Array:
    """x of one lower factor L (n, n) and one (n, k) right-hand side."""
    n, k = b.shape
    size, width = padded_size(n), padded_size(k)
    square = (size, size)
    kernel = functools.partial(_solve_kernel, n=n)
    out = pl.pallas_call(kernel, out_shape=jax.ShapeDtypeStruct((width, size), b.dtype), interpret=interpret,
                         compiler_params=_params(SOLVE_WARPS if num_warps is None else num_warps),
                         name="mjx_morph_cho_solve")(_pad(l, square), _pad(l.T, square), _pad(b.T, (width, size)))
    return out[:k, :n].T


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
    l = c if lower else jnp.swapaxes(c, -1, -2)             # the factor as a lower one (for MJX's upper factor, the
    x = _over_batch(lambda ll, bb: _solve_one(ll, bb, interp, num_warps), batch, l, rhs)  # transposes cancel)
    return x[..., 0] if vector else x
