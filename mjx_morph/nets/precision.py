"""The networks' arithmetic: `precision=fp32|tf32|bf16` (a run's top-level key), the one home of what each means.

| precision | matmul inputs | activations | parameters, optimiser, losses, log-probs, normalisers, recurrent state |
|-----------|---------------|-------------|-------------------------------------------------------------------------|
| fp32      | float32 (XLA precision HIGHEST: what PyTorch computes by default, the original code) | float32 | float32 |
| tf32      | TensorFloat-32 on GPUs that have it (JAX's default on GPU; exact float32 on CPU)     | float32 | float32 |
| bf16      | bfloat16, float32 accumulation                                                       | bfloat16 | float32 |

In bf16 every layer casts its float32 parameters and its input to bfloat16 where it uses them (Flax's `dtype`
convention), so the parameters, their gradients and Adam's moments stay float32. What stays float32 inside the
networks: LayerNorm statistics (Flax reduces in float32), attention logits and softmax, the recurrent cell's
gate non-linearities and its state (h, c carried across steps and rollouts), and the per-limb outputs (mu, value)
that the distribution and the losses read. The physics never follows this key: it runs float32 at the
highest matmul precision (`EnvConfig.matmul_precision`).
"""
from __future__ import annotations

import contextlib
from typing import Iterator

import jax
import jax.numpy as jnp

#: name -> (compute dtype of the networks, JAX default matmul precision for their float32 matmuls)
PRECISIONS: dict[str, tuple[jnp.dtype, str]] = {
    "fp32": (jnp.float32, "highest"),
    "tf32": (jnp.float32, "tensorfloat32"),
    "bf16": (jnp.bfloat16, "default"),
}

#: the original code's arithmetic. Chosen by issue 13's learning comparison (docs/results-log.md, "Precision"; 2
#: seeds x 20 M steps, ft): TF32 ended below fp32's seed range for both R-MoMo and ModuMorph, bf16 within it for
#: R-MoMo (its ModuMorph arm has not run), so neither fast mode is the default yet; both stay one key away.
DEFAULT = "fp32"


def check(precision: str) -> str:
    if precision not in PRECISIONS:
        raise ValueError(f"precision={precision!r}: expected one of {', '.join(PRECISIONS)}")
    return precision


def compute_dtype(precision: str) -> jnp.dtype:
    return PRECISIONS[check(precision)][0]


@contextlib.contextmanager
def scope(precision: str) -> Iterator[None]:
    """Trace the networks' matmuls under this precision (the setting is read when a matmul is traced)."""
    with jax.default_matmul_precision(PRECISIONS[check(precision)][1]):
        yield
