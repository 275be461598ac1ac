"""Generalised advantage estimation with MetaMorph's time-limit semantics.

Per step t the rollout stores the value V_t, the (scaled) reward r_t, `done_t` (the episode ended at this step,
by a fall, an instability or the time limit) and `timeout_t` (it ended by the time limit). With
mask = 1 - done and keep = 1 - timeout, backwards in t:

    delta_t = (r_t + gamma * V_{t+1} * mask_t - V_t) * keep_t
    gae_t   = delta_t + gamma * lambda * mask_t * gae_{t+1}
    ret_t   = gae_t + V_t

so a fall is a true terminal (target r_t), and a time-limit step gets zero advantage and its own value as target
(the original code does not bootstrap from the truncated state). V_T is the value of the observation after the
rollout, computed with the live recurrent state.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp


def gae(values, rewards, dones, timeouts, last_value, gamma: float = 0.99, lam: float = 0.95):
    """values, rewards, dones, timeouts: (T, N); last_value: (N,). Returns (advantages, returns), both (T, N)."""
    mask = 1.0 - dones.astype(jnp.float32)
    keep = 1.0 - timeouts.astype(jnp.float32)
    next_values = jnp.concatenate([values[1:], last_value[None]], axis=0)
    deltas = (rewards + gamma * next_values * mask - values) * keep

    def back(carry, x):
        delta, m = x
        carry = delta + gamma * lam * m * carry
        return carry, carry

    _, adv = jax.lax.scan(back, jnp.zeros_like(last_value), (deltas, mask), reverse=True)
    return adv, adv + values
