"""Matmul FLOPs of a JAX function, counted on its jaxpr, and the peak rates model FLOP utilisation is measured against.

    flops = matmul_flops(jax.make_jaxpr(fn)(*args))

Counted: every `dot_general` (2 x batch x M x N x K), convolutions are not expected here. Loops: a `scan` counts its
body `length` times; a `cond` counts its dearest branch; a `while` counts its body `while_trips` times (its trip count
is not static: the caller says it; the PPO update's one while loop is its minibatches, epochs x minibatches when the KL
stop never fires, the worst case). The MJX solver's while loops are why the physics is not counted. Element-wise work (activations, LayerNorm,
softmax, Adam) is not counted: the figure is the matmul work, the part the matrix units can speed up.

Why not XLA's cost analysis of the compiled program: it counts a while loop's body once, and the update is a loop of
minibatches around loops over time.
"""
from __future__ import annotations

import math
from typing import Any, Optional

import jax
from jax.extend import core as jcore

#: dense peak FLOP/s per matmul precision of the GPUs we run on (NVIDIA data sheets, SXM parts, without sparsity)
PEAK_FLOPS = {
    "H100": {"fp32": 67e12, "tf32": 494.7e12, "bf16": 989.4e12},
    "H200": {"fp32": 67e12, "tf32": 494.7e12, "bf16": 989.4e12},
}


def peak_flops(device_kind: str, precision: str) -> Optional[float]:
    """The device's dense peak for the precision, None when the device is not in the table (a CPU, say)."""
    for name, peaks in PEAK_FLOPS.items():
        if name in device_kind:
            return peaks[precision]
    return None


def _dot_flops(eqn) -> int:
    (lc, rc), (lb, rb) = eqn.params["dimension_numbers"]
    lhs, rhs = (v.aval.shape for v in eqn.invars)
    batch = math.prod(lhs[i] for i in lb)
    contract = math.prod(lhs[i] for i in lc)
    m = math.prod(d for i, d in enumerate(lhs) if i not in lc and i not in lb)
    n = math.prod(d for i, d in enumerate(rhs) if i not in rc and i not in rb)
    return 2 * batch * m * n * contract


def _sub_jaxprs(eqn) -> list[Any]:
    out = []
    for v in eqn.params.values():
        for x in (v if isinstance(v, (tuple, list)) else (v,)):
            if isinstance(x, jcore.ClosedJaxpr):
                out.append(x.jaxpr)
            elif isinstance(x, jcore.Jaxpr):
                out.append(x)
    return out


def matmul_flops(jaxpr: Any, while_trips: int = 1) -> int:
    """Matmul FLOPs of a (closed) jaxpr, loops and branches accounted for as the module docstring says."""
    jaxpr = getattr(jaxpr, "jaxpr", jaxpr)
    total = 0
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        if name == "dot_general":
            total += _dot_flops(eqn)
        elif name == "cond":
            total += max(matmul_flops(b, while_trips) for b in eqn.params["branches"])
        elif name == "scan":
            total += eqn.params["length"] * matmul_flops(eqn.params["jaxpr"], while_trips)
        elif name == "while":
            total += (while_trips * matmul_flops(eqn.params["body_jaxpr"], while_trips)
                      + matmul_flops(eqn.params["cond_jaxpr"], while_trips))
        else:
            total += sum(matmul_flops(j, while_trips) for j in _sub_jaxprs(eqn))
    return total


def count(fn, *args, while_trips: int = 1) -> int:
    """Matmul FLOPs of one call of `fn(*args)` (traced, not run); each while loop's body counts `while_trips` times."""
    return matmul_flops(jax.make_jaxpr(fn)(*args), while_trips)
