"""Learning-rate schedule (MetaMorph's PPO): constant within an iteration i in [0, num_iters),
lr = base * 0.5 * (1 + cos(pi * i / num_iters)), times a linear warm-up factor 0.1 -> 1 over the first
`warmup` iterations (0.10, 0.28, 0.46, 0.64, 0.82 for 5). The cosine runs over the whole horizon."""
from __future__ import annotations

import jax.numpy as jnp


def learning_rate(iteration, num_iters: int, base: float = 3e-4, warmup: int = 5):
    i = jnp.asarray(iteration, jnp.float32)
    lr = base * 0.5 * (1.0 + jnp.cos(jnp.pi * i / num_iters))
    frac = jnp.clip(i / max(warmup, 1), 0.0, 1.0)
    factor = jnp.where(i < warmup, 0.1 * (1.0 - frac) + frac, 1.0)
    return lr * factor
