"""Zero-shot evaluation: all robots of a set, a fixed number of episodes each, in one jitted sweep.

    sweeper = Sweeper(env, model)                       # env holds the robots to evaluate
    res = sweeper(params, obs_rms, robot_ids, episode_ids, seed=0)
    res.ret[i], res.length[i], res.reward[:, i]          # episode of robot robot_ids[i], number episode_ids[i]

What a sweep does (one `lax.scan` over `env.config.episode_length` control steps, all episodes side by side):
- every env starts from `env.reset(key, robot)` with key = fold_in(fold_in(PRNGKey(seed), hash of the robot's name),
  episode), so an episode's result depends only on (seed, robot, episode), not on which other episodes share the
  batch or which set the robot is in (the test: a batched sweep equals stepping each robot alone);
- the policy is deterministic: the action is the Gaussian's mean; observations are normalised with the run's
  frozen statistics; the recurrent state starts at zero;
- each env runs exactly one episode: the env's automatic reset still happens (static shapes), but nothing after
  the first episode end is counted;
- `zero_state_steps` = k holds the recurrent state at zero for the first k steps (the paper's analysis of what the
  recurrence contributes; the previous-action input is left as it is);
- the reward of each of the first `trace_steps` steps is returned per episode (0 after the episode ended), for the
  reward-per-timestep figure.

Large sets run in equal chunks of at most `max_envs` episodes, so one compiled program serves them all.
"""
from __future__ import annotations

import time
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..nets.model import Model
from ..run import normalize_obs
from ..sim.env import Env
from ..unimal.variants import stable_hash


class SweepResult(NamedTuple):
    ret: np.ndarray            # (N,) episode return (raw reward)
    length: np.ndarray         # (N,) control steps
    fell: np.ndarray           # (N,) bool, ended by a fall (or the torso leaving the track, see out_of_bounds)
    out_of_bounds: np.ndarray  # (N,) bool
    timeout: np.ndarray        # (N,) bool, reached the episode length
    unstable: np.ndarray       # (N,) bool, ended by a simulator instability (counted, never trained on)
    reward: np.ndarray         # (trace_steps, N) reward of each early step, 0 after the episode's end


def policy_step(env: Env, model: Model, params, obs_rms, cache, state, carry, reset):
    """One deterministic step of a batch of envs: the Gaussian's mean for the normalised observation, then the env
    step (no sampler: automatic resets draw robots uniformly). -> (next env state, next carry)."""
    obs = normalize_obs(obs_rms, state.obs)
    mu, _, carry = model.step(params, env.robots, obs, carry, reset, cache=cache)
    return env.vstep(state, mu), carry


def episode_keys(seed: int, env: Env, robot_ids: jax.Array, episode_ids: jax.Array) -> jax.Array:
    """Reset keys of episodes `episode_ids` of the env's robots `robot_ids`: a function of (seed, robot name,
    episode), so a robot's episode k is the same in every set that contains the robot."""
    names = np.asarray([stable_hash(m.name) % (2 ** 31) for m in env.morphologies], np.uint32)
    base = jax.random.PRNGKey(seed)
    ids = jnp.asarray(names)[jnp.asarray(robot_ids)]
    return jax.vmap(lambda r, e: jax.random.fold_in(jax.random.fold_in(base, r), e))(ids, jnp.asarray(episode_ids))


class Sweeper:
    def __init__(self, env: Env, model: Model, trace_steps: int = 500, compiler_options: dict | None = None):
        self.env, self.model = env, model
        self.steps = int(env.config.episode_length)
        self.trace_steps = min(int(trace_steps), self.steps)
        self._run = jax.jit(self._sweep, compiler_options=compiler_options)
        self._compiled: dict[int, jax.stages.Compiled] = {}    # chunk -> program compiled ahead (`precompile`)
        self._ran: set[int] = set()                             # chunk sizes called (compiled by the jit)
        self.prepared = ""          # what ran while it was prepared ahead of use ("the run trained"; evaluate.py)

    def precompile(self, params, obs_rms, chunk: int) -> None:
        """Compile the sweep of `chunk` episodes now, for parameters and normalisers shaped like `params` and
        `obs_rms` (arrays or jax.ShapeDtypeStruct), so that the first call of that chunk size does not compile (it may
        run in another thread than the calls: the env build and compilation then overlap other work)."""
        ids = jax.ShapeDtypeStruct((int(chunk),), jnp.int32)
        keys = jax.eval_shape(lambda r, e: episode_keys(0, self.env, r, e), ids, ids)
        self._compiled[int(chunk)] = self._run.lower(params, obs_rms, ids, keys,
                                                     jax.ShapeDtypeStruct((), jnp.int32)).compile()

    def compiled(self, chunk: int) -> bool:
        """Whether the sweep of `chunk` episodes is compiled: ahead (`precompile`) or by an earlier call."""
        return int(chunk) in self._compiled or int(chunk) in self._ran

    def _call(self, chunk: int, *args):
        program = self._compiled.get(chunk)
        if program is not None:
            try:
                return program(*args)
            except (TypeError, ValueError) as e:     # arguments unlike those it was compiled for: compile anew
                del self._compiled[chunk]
                warnings.warn(f"the sweep compiled ahead does not take these arguments ({e}); compiling it again",
                              stacklevel=3)
        self._ran.add(chunk)
        return self._run(*args)

    def _sweep(self, params, obs_rms, robot_ids, keys, zero_state_steps):
        env, model = self.env, self.model
        n = robot_ids.shape[0]
        cache = model.robot_cache(params, env.robots)
        state = env.vreset(keys, robot_ids)
        zero = model.initial_carry(n)
        no = jnp.zeros((n,), bool)
        ep0 = jax.tree.map(lambda x: jnp.zeros((n,), x.dtype), state.ended)

        def body(c, t):
            state, carry, alive, ep = c
            carry = jax.tree.map(lambda z, s: jnp.where(t < zero_state_steps, z, s), zero, carry)
            nxt, carry = policy_step(env, model, params, obs_rms, cache, state, carry, jnp.full((n,), t == 0))
            ends = alive & nxt.done
            ep = jax.tree.map(lambda e, new: jnp.where(ends, new, e), ep, nxt.ended)
            reward = jnp.where(alive, nxt.reward, 0.0)
            return (nxt, carry, alive & ~nxt.done, ep), reward

        c0 = (state, zero, ~no, ep0)
        (_, _, alive, ep), rewards = jax.lax.scan(body, c0, jnp.arange(self.steps))
        return ep, alive, rewards[: self.trace_steps]

    def __call__(self, params, obs_rms, robot_ids, episode_ids, seed: int = 0, zero_state_steps: int = 0,
                 max_envs: int | None = None, progress=None) -> SweepResult:
        """`progress(index, count, episodes, steps, seconds)` is called after each chunk, if given."""
        robot_ids = np.asarray(robot_ids, np.int32)
        episode_ids = np.asarray(episode_ids, np.int32)
        if robot_ids.shape != episode_ids.shape or robot_ids.ndim != 1:
            raise ValueError("robot_ids and episode_ids must be 1-D and of the same length")
        if robot_ids.size and (robot_ids.min() < 0 or robot_ids.max() >= self.env.num_robots):
            raise ValueError(f"robot ids must lie in [0, {self.env.num_robots})")
        n = len(robot_ids)
        chunk = n if not max_envs else min(n, int(max_envs))
        num_chunks = -(-n // chunk)
        pad = num_chunks * chunk - n          # the last chunk is padded with copies of the first episode
        r_all = np.concatenate([robot_ids, np.full(pad, robot_ids[0], np.int32)])
        e_all = np.concatenate([episode_ids, np.full(pad, episode_ids[0], np.int32)])
        parts = []
        for i in range(num_chunks):
            r, e = jnp.asarray(r_all[i * chunk:(i + 1) * chunk]), jnp.asarray(e_all[i * chunk:(i + 1) * chunk])
            t0 = time.perf_counter()
            keys = episode_keys(seed, self.env, r, e)
            ep, alive, rew = self._call(chunk, params, obs_rms, r, keys, jnp.int32(zero_state_steps))
            parts.append(jax.device_get((ep, alive, rew)))
            if progress is not None:
                progress(i, num_chunks, chunk, self.steps, time.perf_counter() - t0)
        cat = lambda xs, axis=0: np.concatenate(xs, axis=axis)
        ep = jax.tree.map(lambda *xs: cat(xs)[:n], *[p[0] for p in parts])
        alive = cat([p[1] for p in parts])[:n]
        rew = cat([p[2] for p in parts], axis=1)[:, :n]
        # an episode still running after episode_length steps cannot happen (the time limit ends it); guard anyway
        if alive.any():
            raise RuntimeError(f"{int(alive.sum())} evaluation episodes did not end within {self.steps} steps")
        return SweepResult(ret=ep.ret.astype(np.float64), length=ep.length.astype(np.int64), fell=ep.fell,
                           out_of_bounds=ep.out_of_bounds, timeout=ep.timeout, unstable=ep.unstable,
                           reward=rew.astype(np.float64))
