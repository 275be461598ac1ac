"""The PPO loss of one minibatch (MetaMorph's PPO, clipped value loss).

    ratio    = exp(logp - logp_old)
    pi_loss  = -mean(min(ratio * A, clip(ratio, 1 - eps, 1 + eps) * A))
    V_clip   = V_old + clip(V - V_old, -eps, eps)
    v_loss   = 0.5 * mean(max((V - R)^2, (V_clip - R)^2))
    loss     = pi_loss + value_coef * v_loss - entropy_coef * entropy
    approx_kl = mean(logp_old - logp)            (computed before the update; drives the early stop)

Means are over all samples of the minibatch.
"""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp


class LossInfo(NamedTuple):
    loss: jnp.ndarray
    pi_loss: jnp.ndarray
    v_loss: jnp.ndarray
    entropy: jnp.ndarray
    approx_kl: jnp.ndarray
    clip_frac: jnp.ndarray
    ratio_mean: jnp.ndarray


def ppo_loss(logp, logp_old, adv, value, value_old, ret, entropy, *, clip_eps: float = 0.2,
             value_coef: float = 0.5, entropy_coef: float = 0.0) -> LossInfo:
    def mean(x):
        return x.sum() / jnp.asarray(x.size, x.dtype)

    log_ratio = logp - logp_old
    ratio = jnp.exp(log_ratio)
    pi_loss = -mean(jnp.minimum(ratio * adv, jnp.clip(ratio, 1 - clip_eps, 1 + clip_eps) * adv))
    v_clip = value_old + jnp.clip(value - value_old, -clip_eps, clip_eps)
    v_loss = 0.5 * mean(jnp.maximum((value - ret) ** 2, (v_clip - ret) ** 2))
    ent = mean(entropy)
    loss = pi_loss + value_coef * v_loss - entropy_coef * ent
    return LossInfo(loss, pi_loss, v_loss, ent, mean(-log_ratio), mean((jnp.abs(ratio - 1) > clip_eps).astype(logp.dtype)),
                    mean(ratio))
