"""Running statistics: observation normalisation and reward scaling (MetaMorph's VecNormalize, in JAX).

- `RunningMeanStd`: per-dimension running mean and variance, initial mean 0, var 1, count 1e-4, merged with each
  new batch by the parallel-variance formula.
- Observation normalisation: `(x - mean) / sqrt(var + 1e-8)`, clipped to [-10, 10]; the statistics are updated with
  every batch of observations *before* it is normalised, and frozen at evaluation.
- Reward scaling: each env keeps a discounted return `R <- gamma R + r` (zeroed when the env's episode ends);
  a scalar running variance of R is updated every step, and PPO sees `clip(r / sqrt(var + 1e-8), -10, 10)`
  (no centring).
"""
from __future__ import annotations

import jax.numpy as jnp
from flax import struct

EPS = 1e-8
CLIP = 10.0


@struct.dataclass
class RunningMeanStd:
    mean: jnp.ndarray
    var: jnp.ndarray
    count: jnp.ndarray

    @classmethod
    def create(cls, shape=()) -> "RunningMeanStd":
        return cls(jnp.zeros(shape, jnp.float32), jnp.ones(shape, jnp.float32), jnp.asarray(1e-4, jnp.float32))

    def update(self, x: jnp.ndarray) -> "RunningMeanStd":
        """Merge a batch `x` of shape (N, *shape)."""
        x = x.astype(jnp.float32)
        n = jnp.asarray(x.shape[0], jnp.float32)
        b_mean, b_var = x.mean(0), x.var(0)
        delta = b_mean - self.mean
        total = self.count + n
        mean = self.mean + delta * n / total
        m2 = self.var * self.count + b_var * n + delta**2 * self.count * n / total
        return RunningMeanStd(mean, m2 / total, total)

    def normalize(self, x: jnp.ndarray, clip: float = CLIP) -> jnp.ndarray:
        return jnp.clip((x - self.mean) / jnp.sqrt(self.var + EPS), -clip, clip)


@struct.dataclass
class RewardScaler:
    """Scales rewards by the running std of each env's discounted return."""
    returns: jnp.ndarray        # (num_envs,)
    stats: RunningMeanStd       # scalar statistics of the discounted returns

    @classmethod
    def create(cls, num_envs: int) -> "RewardScaler":
        return cls(jnp.zeros((num_envs,), jnp.float32), RunningMeanStd.create(()))

    def __call__(self, reward: jnp.ndarray, done: jnp.ndarray, gamma: float) -> tuple["RewardScaler", jnp.ndarray]:
        """Update with this step's raw rewards of all envs; returns the new scaler and the scaled rewards."""
        returns = self.returns * gamma + reward
        stats = self.stats.update(returns)
        scaled = jnp.clip(reward / jnp.sqrt(stats.var + EPS), -CLIP, CLIP)
        return RewardScaler(jnp.where(done, 0.0, returns), stats), scaled
