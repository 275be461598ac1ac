"""A memory task with the MJX env's interface: the reward depends on a cue shown only at the start of an episode.

At its reset an episode draws a cue c = +1 or -1 and shows it once, in column 0 (a state feature, so every
architecture reads it) of every real limb of the first observation; every later observation is noise that does
not depend on c. The reward for the action taken at episode step t is `c * mean(clip(a, -1, 1))` over the robot's
actuators once t >= `reward_from`, else 0; episodes last `length` steps (a time limit). The finished episodes'
statistics report as their return the "late return": the sum of the rewards of steps t >= `score_from` only. The observed previous action
is always zero and no observation depends on the actions, so the cue reaches a late step only through the model's
recurrent state: a feed-forward policy's expected reward is exactly 0, a policy that remembers c gets up to 1 a step.

A step t >= window + burn-in never shares a training sequence (burn-in + window) with its cue: what training
teaches the model about the cue at such a step comes only through the recurrent state stored where the sequence
starts, so `score_from` = window + burn-in scores exactly the steps that need the stored states to be right."""
from __future__ import annotations

import jax
import jax.numpy as jnp

from mjx_morph.layout import Obs, Robots
from mjx_morph.sim import sampling
from toy_env import Episode, EpisodeStats, State   # State: the "physics" here is the episode's cue


class MemoryEnv:
    def __init__(self, length: int = 24, reward_from: int = 1, score_from: int = 12, num_robots: int = 2,
                 noise: float = 0.5):
        if not 0 < reward_from <= score_from < length:
            raise ValueError(f"expected 0 < reward_from ({reward_from}) <= score_from ({score_from}) < length ({length})")
        self.length, self.reward_from, self.score_from = length, reward_from, score_from
        self.num_robots, self.noise = num_robots, noise
        nodes = jnp.arange(12)[None, :] < (3 + jnp.arange(num_robots))[:, None]
        act = jnp.repeat(nodes, 2, axis=1).at[:, :2].set(False)
        ctx = jax.random.normal(jax.random.PRNGKey(3), (num_robots, 12, 35)) * nodes[..., None]
        self.robots = Robots(ctx, nodes, act)
        self.vstep = jax.vmap(self.step, in_axes=(0, 0, None))

    def _obs(self, key, robot, cue) -> Obs:
        node = self.robots.node_mask[robot][:, None]
        x = self.noise * jax.random.normal(key, (12, 52))
        x = x.at[:, 0].set(cue) * node
        return Obs(proprio=x, prev_action=jnp.zeros(24), robot=robot, hfield=jnp.zeros((0,)))

    def reset(self, key, robot):
        k1, k2, k3 = jax.random.split(key, 3)
        cue = jnp.where(jax.random.bernoulli(k1), 1.0, -1.0)
        z, f = jnp.float32(0), jnp.asarray(False)
        ended = EpisodeStats(z, jnp.int32(0), robot, f, f, f, f)
        return State(cue, Episode(robot, jnp.int32(0), z), self._obs(k2, robot, cue), z, f, f, ended, k3)

    def step(self, s: State, action, sampler):
        k1, k2, k3, k4 = jax.random.split(s.key, 4)
        robot, cue = s.episode.robot, s.physics
        mask = self.robots.act_mask[robot]
        a = jnp.where(mask, jnp.clip(action, -1, 1), 0.0)
        r = jnp.where(s.episode.t >= self.reward_from, cue * a.sum() / jnp.maximum(mask.sum(), 1), 0.0)
        t = s.episode.t + 1
        done = t >= self.length
        ret = s.episode.ret + jnp.where(s.episode.t >= self.score_from, r, 0.0)
        f = jnp.asarray(False)
        ended = EpisodeStats(ret, t, robot, f, f, done, f)
        cont = State(cue, Episode(robot, t, ret), self._obs(k1, robot, 0.0), r, done, done, ended, k2)
        fresh = self.reset(k4, sampling.sample(k3, sampler, self.num_robots))
        fresh = fresh._replace(reward=r, done=done, truncated=done, ended=ended)
        return jax.tree.map(lambda n, c: jnp.where(done, n, c), fresh, cont)

    def init(self, key, num_envs, sampler=None):
        """Envs at random steps of their first episode (whose cue they never showed), so that episodes do not
        start in step with the rollout's windows."""
        kr, ke, kt, ko = jax.random.split(key, 4)
        robots = jax.vmap(lambda k: sampling.sample(k, sampler, self.num_robots))(jax.random.split(kr, num_envs))
        s = jax.vmap(self.reset)(jax.random.split(ke, num_envs), robots)
        t0 = jax.random.randint(kt, (num_envs,), 0, self.length)
        obs = jax.vmap(self._obs)(jax.random.split(ko, num_envs), robots, jnp.where(t0 > 0, 0.0, s.physics))
        return s._replace(episode=s.episode._replace(t=t0), obs=obs)
