"""The action distribution: a diagonal Gaussian N(mu, std^2) over the 24 action entries with a frozen,
state-independent std (MetaMorph's ACTION_STD_FIXED, std 0.9).

The std is a constant, not a parameter: it is neither trained nor counted. Entries with `act_mask` False
(torso slots, missing joint slots, padded limbs) are sampled like the rest but dropped by the environment;
their log-probabilities and entropies are excluded (the original sets them to 0 before summing).

Shapes: mu, action, act_mask [..., 24]; results [...] unless said otherwise.
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp

ACTION_STD = 0.9
_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


def sample(key: jax.Array, mu: jax.Array, std: float = ACTION_STD, act_mask: jax.Array | None = None) -> jax.Array:
    """mu + std * N(0, 1). With `act_mask`, masked entries are set to 0 (they are never executed)."""
    a = mu + std * jax.random.normal(key, mu.shape, mu.dtype)
    return a if act_mask is None else jnp.where(act_mask, a, 0.0)


def log_prob_entries(mu: jax.Array, action: jax.Array, std: float = ACTION_STD) -> jax.Array:
    """Per-entry log N(action; mu, std^2) [..., 24]."""
    z = (action - mu) / std
    return -0.5 * z * z - math.log(std) - _LOG_SQRT_2PI


def log_prob(mu: jax.Array, action: jax.Array, act_mask: jax.Array, std: float = ACTION_STD) -> jax.Array:
    """Log-probability of the action, summed over real entries only -> [...]."""
    return jnp.sum(jnp.where(act_mask, log_prob_entries(mu, action, std), 0.0), axis=-1)


def entropy_per_entry(std: float = ACTION_STD) -> float:
    """Entropy of one Gaussian entry, 0.5 + 0.5 log(2 pi) + log std (independent of mu)."""
    return 0.5 + _LOG_SQRT_2PI + math.log(std)


def entropy(mu: jax.Array, act_mask: jax.Array, std: float = ACTION_STD) -> jax.Array:
    """Entropy of the executed part of the distribution: sum over real entries -> [...]."""
    del mu  # the fixed-std Gaussian's entropy does not depend on the mean
    return jnp.sum(act_mask, axis=-1).astype(jnp.float32) * entropy_per_entry(std)


def entropy_metamorph(mu: jax.Array, act_mask: jax.Array, std: float = ACTION_STD) -> jax.Array:
    """The original's entropy term: per-entry entropy with masked entries zeroed, averaged over all
    batch x 24 entries -> scalar. Its coefficient is 0 in the paper's runs."""
    del mu
    return jnp.mean(jnp.where(act_mask, entropy_per_entry(std), 0.0))


def kl_divergence(mu_p: jax.Array, mu_q: jax.Array, act_mask: jax.Array, std: float = ACTION_STD) -> jax.Array:
    """KL(N(mu_p, std) || N(mu_q, std)) summed over real entries -> [...]."""
    d = (mu_p - mu_q) / std
    return jnp.sum(jnp.where(act_mask, 0.5 * d * d, 0.0), axis=-1)
