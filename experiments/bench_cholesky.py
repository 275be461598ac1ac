"""MJX's batched Cholesky alone: JAX's `cho_factor` / `cho_solve` against the fused Pallas kernels (env.linalg).

    python -m experiments.bench_cholesky                       # on the GPU machine: B = 32 ... 1024, n = 58
    python -m experiments.bench_cholesky n=64 'batches=[64,4096]' reps=500
    python -m experiments.bench_cholesky 'warps=[1,2,4,8]'           # also pallas with each warp count

As MJX calls them (sim/gpu_linalg.py): B random SPD float32 matrices of size n, the upper factor (lower=False) and a
vector right-hand side, vmapped over B; times the factorisation alone, the solve alone, and both in one program
(the device's milliseconds a call: `reps` calls chained in one compiled loop, as MJX's solver loops call them, so
that the host's dispatch, ~0.1 ms and most of a single call's time at small B, is left out), for `jax`
(cuSOLVER's potrf and cuBLAS's trsm on a GPU) and `pallas` (one Triton kernel each), and prints the device kernels
each compiled program calls (custom calls: cuSOLVER, cuBLAS, Triton) and the largest difference of pallas' solution
from jax's (relative to its largest entry). `warps=` adds a pallas row for each count of warps a program, the
factor's and the solve's alike (defaults: `gpu_linalg.num_warps_for`, 4 at n = 58, for the factor;
`gpu_linalg.SOLVE_WARPS` for the solve). On a CPU the Pallas kernels run interpreted: the numbers then say nothing
about the GPU.
"""
from __future__ import annotations

import dataclasses
import functools
import re
import sys
import time
from typing import List

import jax
import jax.numpy as jnp
import numpy as np

from mjx_morph.run import register
from mjx_morph.sim import gpu_linalg

from . import cli


@dataclasses.dataclass
class BenchCholeskyConfig:
    n: int = 58                              # matrix size (the 100 train robots' padded nv)
    batches: List[int] = dataclasses.field(default_factory=lambda: [32, 64, 128, 256, 512, 1024])  # matrices a call
    reps: int = 200                          # calls in a timed loop (the median of 5 loops is printed)
    warps: List[int] = dataclasses.field(default_factory=list)    # also pallas with each of these warp counts


register("bench_cholesky_schema", BenchCholeskyConfig)


def _impls(warps):
    """(name, cho_factor, cho_solve) of each case: JAX's, the kernels as env.linalg=pallas runs them, and each
    warp count asked for."""
    out = [("jax", jax.scipy.linalg.cho_factor, jax.scipy.linalg.cho_solve),
           ("pallas", gpu_linalg.cho_factor, gpu_linalg.cho_solve)]
    for w in warps:
        out.append((f"pallas/w{w}", functools.partial(gpu_linalg.cho_factor, num_warps=w),
                    functools.partial(gpu_linalg.cho_solve, num_warps=w)))
    return out


def _looped(fn, reps: int):
    """`fn` (arrays -> one array) called `reps` times in one compiled loop, each call's inputs nudged by 1e-30 of
    the last call's first output entry (so XLA can neither hoist nor drop a call): the device's time per call,
    without the host's dispatch (which dominates a single call of a small batch)."""
    def run(*args):
        def body(_, carry):
            nudge = 1e-30 * fn(*carry).reshape(-1)[0]
            return tuple(x + nudge for x in carry)
        return jax.lax.fori_loop(0, reps, body, args)
    return jax.jit(run)


def _time(fn, *args, reps: int) -> float:
    """Milliseconds of device time per call of `fn` (median of 5 timings of a loop of `reps` calls)."""
    loop = _looped(fn, reps)
    jax.block_until_ready(loop(*args))
    times = []
    for _ in range(5):
        t = time.perf_counter()
        jax.block_until_ready(loop(*args))
        times.append(time.perf_counter() - t)
    return float(np.median(times)) * 1e3 / reps


def _kernels(compiled) -> str:
    targets = re.findall(r'custom_call_target="([^"]+)"', compiled.as_text())
    return ",".join(sorted(set(targets))) or "-"


def bench(cfg: BenchCholeskyConfig) -> None:
    n, batches, reps, warps = cfg.n, list(cfg.batches), cfg.reps, list(cfg.warps)
    size = gpu_linalg.padded_size(n)
    print(f"# jax {jax.__version__} on {jax.devices()[0].device_kind}; n={n} (pallas pads to {size}; warps: factor "
          f"{gpu_linalg.num_warps_for(size)}, solve {gpu_linalg.SOLVE_WARPS}), float32, upper factor, vector b; "
          f"device time a call (loops of {reps} calls), ms")
    print(f"{'B':>6} {'impl':10} {'factor':>9} {'solve':>9} {'both':>9}  {'max rel diff':>12}  kernels")
    for b in batches:
        k1, k2 = jax.random.split(jax.random.PRNGKey(b))
        m = jax.random.normal(k1, (b, n, n), jnp.float32)
        a = m @ jnp.swapaxes(m, -1, -2) / n + jnp.eye(n, dtype=jnp.float32)
        rhs = jax.random.normal(k2, (b, n), jnp.float32)
        results = {}
        for name, factor, solve in _impls(warps):
            f = jax.vmap(lambda x, factor=factor: factor(x)[0])
            s = jax.vmap(lambda c, y, solve=solve: solve((c, False), y))
            both = jax.vmap(lambda x, y, factor=factor, solve=solve: solve(factor(x), y))
            c = jax.jit(f)(a)
            row = [_time(f, a, reps=reps), _time(s, c, rhs, reps=reps), _time(both, a, rhs, reps=reps)]
            compiled = jax.jit(both).lower(a, rhs).compile()
            results[name] = np.asarray(compiled(a, rhs))
            diff = ""
            if name != "jax":
                diff = f"{np.abs(results[name] - results['jax']).max() / np.abs(results['jax']).max():.1e}"
            print(f"{b:6d} {name:10} {row[0]:9.4f} {row[1]:9.4f} {row[2]:9.4f}  {diff:>12}  {_kernels(compiled)}",
                  flush=True)


def main(argv=None) -> int:
    return cli.main(bench, "bench_cholesky_schema", BenchCholeskyConfig, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
