"""MJX's batched Cholesky alone: JAX's `cho_factor` / `cho_solve` against the fused Pallas kernels (env.linalg).

    python -m experiments.bench_cholesky                       # on the GPU machine: B = 64 and 1024, n = 58
    python -m experiments.bench_cholesky n=64 'batches=[64,4096]' reps=100
    python -m experiments.bench_cholesky 'warps=[1,2,4,8]'           # also pallas with each warp count

As MJX calls them (sim/gpu_linalg.py): B random SPD float32 matrices of size n, the upper factor (lower=False) and a
vector right-hand side, vmapped over B; times the factorisation alone, the solve alone, and both in one program
(milliseconds a call, the median of `reps` calls after a warm-up), for `jax` (cuSOLVER's potrf and cuBLAS's trsm on
a GPU) and `pallas` (one Triton kernel each), and prints the device kernels each compiled program calls (custom
calls: cuSOLVER, cuBLAS, Triton) and the largest difference of pallas' solution from jax's (relative to its largest
entry). `warps=` adds a pallas row for each count of warps a program (default: `gpu_linalg.num_warps_for`, 4 at
n = 58). On a CPU the Pallas kernels run interpreted: the numbers then say nothing about the GPU.
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
    batches: List[int] = dataclasses.field(default_factory=lambda: [64, 1024])   # matrices a call (envs)
    reps: int = 50                           # timed calls per case (the median is printed)
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


def _time(fn, *args, reps: int) -> float:
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return float(np.median(times)) * 1e3


def _kernels(compiled) -> str:
    targets = re.findall(r'custom_call_target="([^"]+)"', compiled.as_text())
    return ",".join(sorted(set(targets))) or "-"


def bench(cfg: BenchCholeskyConfig) -> None:
    n, batches, reps, warps = cfg.n, list(cfg.batches), cfg.reps, list(cfg.warps)
    size = gpu_linalg.padded_size(n)
    print(f"# jax {jax.__version__} on {jax.devices()[0].device_kind}; n={n} (pallas pads to {size}, "
          f"{gpu_linalg.num_warps_for(size)} warps), float32, upper factor, vector b; median of {reps} calls, ms")
    print(f"{'B':>6} {'impl':10} {'factor':>9} {'solve':>9} {'both':>9}  {'max rel diff':>12}  kernels")
    for b in batches:
        k1, k2 = jax.random.split(jax.random.PRNGKey(b))
        m = jax.random.normal(k1, (b, n, n), jnp.float32)
        a = m @ jnp.swapaxes(m, -1, -2) / n + jnp.eye(n, dtype=jnp.float32)
        rhs = jax.random.normal(k2, (b, n), jnp.float32)
        results = {}
        for name, factor, solve in _impls(warps):
            f = jax.jit(jax.vmap(lambda x, factor=factor: factor(x)[0]))
            s = jax.jit(jax.vmap(lambda c, y, solve=solve: solve((c, False), y)))
            both = jax.jit(jax.vmap(lambda x, y, factor=factor, solve=solve: solve(factor(x), y))).lower(
                a, rhs).compile()
            c = f(a)
            row = [_time(f, a, reps=reps), _time(s, c, rhs, reps=reps), _time(both, a, rhs, reps=reps)]
            results[name] = np.asarray(both(a, rhs))
            diff = ""
            if name != "jax":
                diff = f"{np.abs(results[name] - results['jax']).max() / np.abs(results['jax']).max():.1e}"
            print(f"{b:6d} {name:10} {row[0]:9.3f} {row[1]:9.3f} {row[2]:9.3f}  {diff:>12}  {_kernels(both)}",
                  flush=True)


def main(argv=None) -> int:
    return cli.main(bench, "bench_cholesky_schema", BenchCholeskyConfig, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
