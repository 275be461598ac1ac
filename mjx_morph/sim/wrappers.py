"""Training-time behaviour around the task env (`env.UnimalEnv`), as brax / MuJoCo Playground wrap their envs.

`AutoReset(env)`: what `make_env` returns and the trainer and the evaluation use.
    step(state, action, sampler=None)   the task's step; where it ends the episode (`done`), the env is reset at
                                        once into a robot drawn from `sampler.probs` (uniform without a sampler)
                                        with a new terrain. The returned `reward`, `done`, `truncated` and `ended`
                                        are the transition's, everything else is the new episode's first state
                                        (MetaMorph's vectorised envs reset the same way).
    vreset(keys, robots), vstep(states, actions, sampler), init(key, num_envs, sampler)   batched versions.
Every other attribute (`robots`, `num_robots`, `sm`, `config`, `task`, `terrain`, `morphologies`, `observe`, ...)
is the wrapped env's.

Keys: each step splits the state's key into (next key, robot draw, reset), the reset splits its key as
`UnimalEnv.reset` does; the env's random stream is a function of its initial key and the sampler's probabilities.
"""
from __future__ import annotations

from typing import Any, Protocol

import jax
import jax.numpy as jnp

from . import sampling

# The wrapped env's state (`env.EnvState`): a NamedTuple with at least `key`, `reward`, `done`, `truncated` and
# `ended`. Named here, not imported: env.py imports this module, and imports only go down.
TaskState = Any


class TaskEnv(Protocol):
    """What `AutoReset` needs of the env it wraps (`env.UnimalEnv`): a reset into a given robot and a step that
    does not reset."""
    num_robots: int

    def reset(self, key: jax.Array, robot: jax.Array) -> TaskState: ...

    def step(self, state: TaskState, action: jax.Array) -> TaskState: ...


class AutoReset:
    def __init__(self, env: TaskEnv):
        self.env = env

    def __getattr__(self, name):
        if name == "env":                  # not set yet (e.g. while unpickling): no recursion
            raise AttributeError(name)
        return getattr(self.env, name)

    def reset(self, key: jax.Array, robot: jax.Array) -> TaskState:
        return self.env.reset(key, robot)

    def step(self, state: TaskState, action: jax.Array, sampler: sampling.SamplerState | None = None) -> TaskState:
        key, k_robot, k_reset = jax.random.split(state.key, 3)
        nxt = self.env.step(state, action)._replace(key=key)
        fresh = self.env.reset(k_reset, sampling.sample(k_robot, sampler, self.env.num_robots))
        fresh = fresh._replace(reward=nxt.reward, done=nxt.done, truncated=nxt.truncated, ended=nxt.ended)
        return jax.tree_util.tree_map(lambda a, b: jnp.where(nxt.done, a, b), fresh, nxt)

    def vreset(self, keys: jax.Array, robots: jax.Array) -> TaskState:
        """Batched `reset` (keys (N, 2), robots (N,))."""
        return jax.vmap(self.reset)(keys, robots)

    def vstep(self, state: TaskState, action: jax.Array, sampler: sampling.SamplerState | None = None) -> TaskState:
        """Batched `step` over the leading env axis of `state` and `action` (N, 24); one sampler for all."""
        return jax.vmap(self.step, in_axes=(0, 0, None))(state, action, sampler)

    def init(self, key: jax.Array, num_envs: int, sampler: sampling.SamplerState | None = None) -> TaskState:
        """`num_envs` fresh envs, robots drawn from the sampler (uniform without one)."""
        kr, ke = jax.random.split(key)
        robots = jax.vmap(lambda k: sampling.sample(k, sampler, self.env.num_robots))(jax.random.split(kr, num_envs))
        return self.vreset(jax.random.split(ke, num_envs), robots)
