"""A cheap stand-in for the MJX env with the same interface (for testing the PPO bookkeeping quickly).

Observations drift at random, episodes end by a "fall" (random) or a time limit that depends on the robot, the
reward depends on the action; robots differ in their limb and actuator masks."""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from mjx_morph.layout import Obs, Robots
from mjx_morph.sim import sampling
from mjx_morph.sim.env import EpisodeStats   # the real env's statistics, so the trainer reads the same fields
from mjx_morph.sim.model import model_digest


class Episode(NamedTuple):
    robot: jax.Array
    t: jax.Array
    ret: jax.Array


class State(NamedTuple):
    """The real EnvState's layout, with the drifting observation as the "physics"."""
    physics: jax.Array
    episode: Episode
    obs: Obs
    reward: jax.Array
    done: jax.Array
    truncated: jax.Array
    ended: EpisodeStats
    key: jax.Array


class ToyEnv:
    def __init__(self, num_robots: int = 3, limits=(5, 9, 13), fall_prob: float = 0.05):
        self.num_robots = num_robots
        self.limits = jnp.asarray(limits[:num_robots], jnp.int32)
        self.fall_prob = fall_prob
        nodes = jnp.arange(12)[None, :] < (4 + 2 * jnp.arange(num_robots))[:, None]
        act = jnp.repeat(nodes, 2, axis=1).at[:, :2].set(False).at[:, 3::4].set(False)
        ctx = jax.random.normal(jax.random.PRNGKey(7), (num_robots, 12, 35)) * nodes[..., None]
        self.robots = Robots(ctx, nodes, act)
        self.vstep = jax.vmap(self.step, in_axes=(0, 0, None))
        # what a run records of the physics it trained on (as UnimalEnv.digest)
        self.digest = model_digest(limits=self.limits, fall_prob=fall_prob, robots=self.robots)

    def reset(self, key, robot):
        k1, k2 = jax.random.split(key)
        x = jax.random.normal(k1, (12, 52)) * self.robots.node_mask[robot][:, None]
        obs = Obs(proprio=x, prev_action=jnp.zeros(24), robot=robot, hfield=jnp.zeros((0,)))
        z, f = jnp.float32(0), jnp.asarray(False)
        ended = EpisodeStats(z, jnp.int32(0), robot, f, f, f, f)
        return State(x, Episode(robot, jnp.int32(0), z), obs, z, f, f, ended, k2)

    def step(self, s: State, action, sampler):
        k1, k2, k3, k4 = jax.random.split(s.key, 4)
        robot = s.episode.robot
        mask = self.robots.act_mask[robot]
        a = jnp.where(mask, jnp.clip(action, -1, 1), 0.0)
        x = (0.9 * s.physics + 0.3 * jax.random.normal(k1, s.physics.shape)
             + 0.1 * a.reshape(12, 2).sum(-1, keepdims=True))
        x = x * self.robots.node_mask[robot][:, None]
        r = a.sum() * 0.1 + x[0, 0]
        t = s.episode.t + 1
        fell = jax.random.uniform(k2) < self.fall_prob
        timeout = (t >= self.limits[robot]) & ~fell
        done = fell | timeout
        ret = s.episode.ret + r
        ended = EpisodeStats(ret, t, robot, fell, jnp.asarray(False), timeout, jnp.asarray(False))
        obs = Obs(proprio=x, prev_action=a, robot=robot, hfield=jnp.zeros((0,)))
        cont = State(x, Episode(robot, t, ret), obs, r, done, timeout, ended, k3)
        fresh = self.reset(k4, sampling.sample(k3, sampler, self.num_robots))
        fresh = fresh._replace(reward=r, done=done, truncated=timeout, ended=ended)
        return jax.tree.map(lambda f, c: jnp.where(done, f, c), fresh, cont)

    def init(self, key, num_envs, sampler=None):
        kr, ke = jax.random.split(key)
        robots = jax.vmap(lambda k: sampling.sample(k, sampler, self.num_robots))(jax.random.split(kr, num_envs))
        return jax.vmap(self.reset)(jax.random.split(ke, num_envs), robots)
