"""Work around a deadlock of jaxlib 0.10's CPU LAPACK kernels under MJX: pure-JAX Cholesky for MJX on CPU.

jaxlib 0.10.x runs batched LAPACK calls (`potrf` for `cho_factor`, ...) through `jax::ParallelBatchMap`, which
schedules batch chunks onto XLA:CPU's intra-op thread pool and blocks waiting for them. When the thunk executor
has several such calls in flight they occupy every pool thread and wait for work nobody can run: the process
hangs at 0% CPU (seen here with MJX's Newton solver vmapped over 60 robots on the 2-core CI machine; gdb shows
all pool threads in `BlockingCounter::Wait` under `CholeskyFactorization`). jaxlib 0.11 compiles that parallel
path out of open-source builds, and GPUs never take it.

`applies()` says whether the workaround is needed (jaxlib older than 0.11 and the default backend a CPU, looked
at while a step is traced, so importing the package does not initialise JAX's backends); then linalg.py, the one
place MJX is given its Cholesky, gives MJX's modules that factor or solve with it (smooth, solver, forward) these
plain JAX loops for the default `env.linalg=jax` (`lax.fori_loop` over the columns; exact to float rounding,
O(n^3) like LAPACK, fine for the nv <= ~60 of padded UNIMALs) and JAX's own functions otherwise.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp


def cholesky_upper(a: jax.Array) -> jax.Array:
    """U with a = U^T U (upper triangle, zeros below), for a symmetric positive definite `a` (..., n, n)."""
    n = a.shape[-1]
    idx = jnp.arange(n)

    def col(j, L):       # build lower L column by column, return its transpose
        row = L[..., j, :] * (idx < j)                                    # L[j, :j]
        d = jnp.sqrt(jnp.maximum(a[..., j, j] - jnp.sum(row * row, axis=-1), 1e-30))
        s = a[..., :, j] - jnp.einsum("...ik,...k->...i", L * (idx < j), row)
        c = jnp.where(idx > j, s / d[..., None], 0.0) + jnp.where(idx == j, d[..., None], 0.0)
        return L.at[..., :, j].set(c)

    L = jax.lax.fori_loop(0, n, col, jnp.zeros_like(a))
    return jnp.swapaxes(L, -1, -2)


def _solve_upper(u: jax.Array, b: jax.Array, transpose: bool) -> jax.Array:
    """Solve U x = b (transpose=False, back substitution) or U^T x = b (forward substitution)."""
    n = u.shape[-1]
    idx = jnp.arange(n)
    vec = b.ndim == u.ndim - 1
    x = b[..., None] if vec else b

    def step(k, x):
        i = k if transpose else n - 1 - k
        if transpose:
            coeff = u[..., :, i] * (idx < i)                 # U^T[i, :i] = U[:i, i]
        else:
            coeff = u[..., i, :] * (idx > i)
        v = (x[..., i, :] - jnp.einsum("...k,...kj->...j", coeff, x)) / u[..., i, i][..., None]
        return x.at[..., i, :].set(v)

    x = jax.lax.fori_loop(0, n, step, x)
    return x[..., 0] if vec else x


def cho_factor(a, lower=False, overwrite_a=False, check_finite=True):
    u = cholesky_upper(jnp.asarray(a))
    return (jnp.swapaxes(u, -1, -2) if lower else u), lower


def cho_solve(c_and_lower, b, overwrite_b=False, check_finite=True):
    c, lower = c_and_lower
    u = jnp.swapaxes(c, -1, -2) if lower else c
    return _solve_upper(u, _solve_upper(u, jnp.asarray(b), transpose=True), transpose=False)


def _affected_jaxlib() -> bool:
    try:
        major, minor = (int(x) for x in jax.__version__.split(".")[:2])
    except ValueError:
        return False
    return (major, minor) < (0, 11)


def applies() -> bool:
    """Whether MJX's "jax" Cholesky should be these loops: jaxlib < 0.11 with the default backend a CPU (call it
    while tracing)."""
    return _affected_jaxlib() and jax.default_backend() == "cpu"


_JAX = (jax.scipy.linalg.cho_factor, jax.scipy.linalg.cho_solve)


def default_functions():
    """(cho_factor, cho_solve) of `env.linalg=jax`: these loops where `applies()`, JAX's own otherwise (call it while
    tracing). Also what the Pallas kernels (gpu_linalg.py) fall back to for what they do not handle."""
    return (cho_factor, cho_solve) if applies() else _JAX
