"""The hypernetwork's per-sample product two ways: `nets.network.gathered_matvec` against `jax.lax.ragged_dot`.

    python -m experiments.bench_hn_matmul            # on the GPU machine; prints one line per case

Each sample n needs x[n, l] @ W[robot[n], l] with W the per-robot tables [R, 12, in, out] (R-MoMo's embedding: R =
100, in 54, out 128). `gather` is the code's own `gathered_matvec` (einsum over the gathered table, cast to the
compute dtype after the gather; its gradient is a float32 scatter-add); `ragged` sorts the (sample, limb) rows by
(robot, limb) and calls `jax.lax.ragged_dot` over the 1,200 groups, which would read each table once and give its
gradient without a scatter-add if XLA lowers it to a grouped GEMM. Times one jitted forward + backward (gradients for
x and the table) for a burn-in-sized (1,280) and a minibatch-sized (6,400) batch, float32 / TF32 / bf16, and names the
kernels the compiled program calls. A case that fails to compile (XLA's dense fallback can ask for tens of GB) prints
its error and the rest go on. Rerun it on a new JAX: if `ragged` ever beats `gather`, it is the lever
docs/benchmarks.md (issue 13, session 14) names.
"""
from __future__ import annotations

import re
import time

import jax
import jax.numpy as jnp
from mjx_morph.nets.network import gathered_matvec

R, L, I, O = 100, 12, 54, 128


def ragged(x, table, idx, dtype=jnp.float32):
    """`gathered_matvec` as one grouped matmul over the (robot, limb) groups."""
    n = x.shape[0]
    group = (idx[:, None] * L + jnp.arange(L)[None, :]).reshape(-1)
    order = jnp.argsort(group)
    sizes = jnp.bincount(group, length=R * L).astype(jnp.int32)
    ys = jax.lax.ragged_dot(x.reshape(n * L, I)[order].astype(dtype), table.reshape(R * L, I, O).astype(dtype), sizes)
    return jnp.zeros_like(ys).at[order].set(ys).reshape(n, L, O)


def main() -> None:
    print(f"# jax {jax.__version__} on {jax.devices()[0].device_kind}; R={R} L={L} in={I} out={O}")
    for n in (1280, 6400):
        k1, k2, k3 = jax.random.split(jax.random.PRNGKey(0), 3)
        x, table = jax.random.normal(k1, (n, L, I)), jax.random.normal(k2, (R, L, I, O))
        idx = jax.random.randint(k3, (n,), 0, R)
        for name, f in (("gather", gathered_matvec), ("ragged", ragged)):
            for prec in ("highest", "tensorfloat32", "bf16"):
                def loss(x, t, f=f, prec=prec):
                    dtype = jnp.bfloat16 if prec == "bf16" else jnp.float32
                    with jax.default_matmul_precision("default" if prec == "bf16" else prec):
                        return (f(x, t, idx, dtype).astype(jnp.float32) ** 2).sum()
                try:
                    c = jax.jit(jax.grad(loss, argnums=(0, 1))).lower(x, table).compile()
                except Exception as e:      # noqa: BLE001 - report and go on
                    print(f"N={n} {name:7s} {prec:13s} failed to compile: {str(e).splitlines()[0][:160]}", flush=True)
                    continue
                kernels = sorted(set(re.findall(r"ragged_dot[a-z_]*|__cublas\$lt\$matmul", c.as_text())))
                jax.block_until_ready(c(x, table))
                t = time.perf_counter()
                for _ in range(20):
                    out = c(x, table)
                jax.block_until_ready(out)
                ms = (time.perf_counter() - t) / 20 * 1e3
                print(f"N={n} {name:7s} {prec:13s} forward + backward {ms:8.3f} ms  {kernels}", flush=True)


if __name__ == "__main__":
    main()
