"""Chunked recurrent PPO as one jitted function of a single train state; docs/architecture.md shows where it sits.

One iteration (`Trainer.iteration`, jitted; `rollout` and `update` are its two halves, jitted separately for
per-phase timing):

1. Rollout: `lax.scan` over control steps. Each step updates the observation normaliser with the batch,
   normalises the proprioceptive part, runs `model.step` with the carried per-limb state (zeroed at episode
   starts), samples from N(mu, 0.9), steps every env (automatic resets draw robots from the sampler), and scales
   the reward. Env state, recurrent state, normalisers and the sampler carry across iterations, so episodes run
   across rollout boundaries.
2. Windows: the rollout of T steps per env is cut into T / W windows of W = 80 steps. Window k is trained as a
   sequence of B = 20 burn-in steps followed by its W steps, from the recurrent state stored where its burn-in
   starts. The scan records that state (one per window), so only K = T / W states per env are stored, not T.
   The first window's burn-in is the last B steps of the previous rollout (kept in the train state as the "tail").
   Done flags reset the state inside burn-in and window alike.
   Feed-forward models use the same code with W = 1 and B = 0: windows are single transitions, shuffled
   individually as in the original PPO.
3. GAE (γ 0.99, λ 0.95, time-limit semantics) with V(s_T) from the live state; advantages normalised once over
   the whole rollout.
4. Epochs x minibatches (whole windows, a fresh permutation per epoch) as one `lax.while_loop`. Before each update
   the approximate KL on the minibatch is computed with the current parameters (the same forward pass as the
   gradient); if it exceeds the threshold that update is not applied and the loop ends: the remaining minibatches
   and epochs are not computed.
5. The robot sampler folds in the rollout's finished episodes once per iteration.

Everything is device-side; the Python loop only logs, checkpoints and evaluates.

Several devices (`devices=N`): the arrays with an env axis (env state, recurrent states, tails, the batch) are
sharded over a one-axis mesh ("env"), everything else (parameters, optimiser, normalisers, sampler, keys) is
replicated, and the jitted functions keep that layout. The program is the same global program: XLA partitions it,
so minibatches are drawn from all envs, gradients, the KL stop, the normalisers and the sampler see every device's
data, and N devices compute what one device computes for the same global batch (up to the order of summation).

Several seeds in one program (`seeds=S`): the train state gets a leading seed axis and every jitted function is the
single-seed function under `jax.vmap`, so seed i computes what a run of seed i alone computes. The seeds are
independent: the KL stop is per seed (the update loop runs while some seed still updates; a stopped seed's
parameters no longer change). With several devices the mesh is ("seed", "env"): the seed axis is spread over
gcd(S, devices) devices (no communication between them) and each seed's envs over the rest.
Several processes (hosts, `mjx_morph/run/distributed.py`) are the same: the mesh spans every process's devices, each
process steps the envs of its own, and the metrics come out replicated, so every process can read them.
"""
from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from ..layout import Obs
from ..nets.model import Model
from ..sim import sampling
from ..sim.env import Env
from .config import PPOConfig
from .gae import gae
from .loss import LossInfo, ppo_loss
from .schedule import learning_rate
from .stats import RewardScaler, RunningMeanStd


@struct.dataclass
class TrainState:
    params: Any
    opt_state: Any
    obs_rms: RunningMeanStd      # over the flattened 12 x 52 proprioceptive vector
    rew: RewardScaler
    env: Any                     # batched EnvState
    carry: Any                   # per-env recurrent state before the current observation
    first: jax.Array             # (N,) the current observation starts an episode
    tail_obs: Obs                # last B normalised observations of the previous rollout, (B, N, ...)
    tail_first: jax.Array        # (B, N)
    tail_carry: Any              # recurrent state where the tail starts
    sampler: sampling.SamplerState
    key: jax.Array
    iteration: jax.Array         # () int32, iterations done


class Batch(NamedTuple):
    """A rollout, time-major (T, N), plus what the windows need."""
    obs: Obs                     # (B + T, N, ...) normalised: tail then rollout
    first: jax.Array             # (B + T, N)
    starts: Any                  # (K, N, ...) recurrent state at each window's burn-in start
    action: jax.Array            # (T, N, 24)
    logp: jax.Array              # (T, N)
    value: jax.Array             # (T, N)
    adv: jax.Array               # (T, N) normalised
    ret: jax.Array               # (T, N)


class ActCarry(NamedTuple):
    """What one rollout step carries to the next."""
    env: Any                     # batched EnvState
    carry: Any                   # per-env recurrent state before the current observation
    first: jax.Array             # (N,) the current observation starts an episode
    obs_rms: RunningMeanStd
    rew: RewardScaler


class Minibatch(NamedTuple):
    """Windows of a batch as time-major sequences of B + W steps (M windows), and their PPO targets (W, M)."""
    obs: Obs                     # (B + W, M, ...)
    first: jax.Array             # (B + W, M)
    carry0: Any                  # (M, ...) recurrent state where each burn-in starts
    action: jax.Array
    logp: jax.Array
    value: jax.Array
    adv: jax.Array
    ret: jax.Array


class SGDCarry(NamedTuple):
    """What one minibatch update carries to the next (all epochs' minibatches are one loop)."""
    step: jax.Array              # () int32, the next minibatch
    params: Any
    opt_state: Any
    stopped: jax.Array           # the KL stop fired: every later minibatch is skipped
    acc: LossInfo                # sums over the applied minibatches
    applied: jax.Array           # () int32 minibatches applied
    first_info: LossInfo         # loss statistics of the first minibatch (ratio 1, KL 0 with fresh rollouts)


class Transition(NamedTuple):
    obs: Obs
    first: jax.Array
    action: jax.Array
    logp: jax.Array
    value: jax.Array
    reward: jax.Array            # scaled
    raw_reward: jax.Array
    done: jax.Array
    truncated: jax.Array
    ep_return: jax.Array
    ep_length: jax.Array
    ep_robot: jax.Array
    unstable: jax.Array
    fell: jax.Array


#: XLA CPU options for small programs whose compile time dominates (tests, smoke runs): ~2x faster compiles. XLA's
#: newer CPU fusion emitters (MLIR) are off too, which compiles and runs these unoptimised programs faster (and an
#: optimised one slower: not a default elsewhere; docs/benchmarks.md, "CPU notes", session 36)
FAST_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True,
                "xla_cpu_use_fusion_emitters": False}


def normalize_obs(rms: RunningMeanStd, env_obs) -> Obs:
    """The model's input from a batch (N, ...) of env observations: the proprioceptive part normalised with `rms`
    (flattened to 12 x 52 values per env), the rest as it is."""
    p = env_obs.proprio
    flat = rms.normalize(p.reshape(p.shape[0], -1))
    return Obs(flat.reshape(p.shape), env_obs.prev_action, env_obs.robot, env_obs.hfield)


class Trainer:
    """Chunked recurrent PPO for one env and one model; `total_steps` sets the learning-rate schedule's horizon."""

    def __init__(self, env: Env, model: Model, config: PPOConfig, total_steps: int, fast_compile: bool = False,
                 devices: int | None = 1, seeds: int | None = None):
        """`seeds`: None for one run; S for S independent runs side by side (a leading seed axis of size S on the
        train state, the batch and the metrics; `init` then takes S keys)."""
        config = config.for_model(model.recurrent)
        config.check()
        self.env, self.model, self.cfg = env, model, config
        self.total_steps = int(total_steps)
        self.num_iters = config.iterations(self.total_steps)
        self.num_windows = config.rollout_len // config.window      # K per env
        self.mb_windows = config.minibatch_size // config.window
        self.num_minibatches = config.num_envs * self.num_windows // self.mb_windows
        self.tx = optax.inject_hyperparams(
            lambda learning_rate: optax.chain(optax.clip_by_global_norm(config.max_grad_norm),
                                              optax.adam(learning_rate, eps=config.adam_eps)))(learning_rate=config.lr)
        if seeds is not None and int(seeds) < 1:
            raise ValueError(f"seeds={seeds}: expected a positive number of seeds or None")
        self.num_seeds = None if seeds is None else int(seeds)
        self.mesh = device_mesh(devices, config.num_envs, self.num_seeds)
        self.blocks = minibatch_blocks(config, self.mb_windows, 1 if self.mesh is None else self.mesh.shape["env"])
        # with the envs sharded, the networks take a window's rows batch-major so the batch stays sharded
        self.batch_major = self.mesh is not None
        opts = dict(compiler_options=FAST_COMPILE) if fast_compile else {}
        seeded = self.num_seeds is not None
        if self.mesh is None:
            jit = lambda f, **_: jax.jit(f, **opts)
            self._state_sharding = bt = rep = None
        else:
            jit = lambda f, out: jax.jit(f, out_shardings=out, **opts)
            self._state_sharding = state_sharding(self.mesh, seeded)
            # every batch field is time-major (time, env, ...)
            bt = NamedSharding(self.mesh, P("seed", None, "env") if seeded else P(None, "env"))
            rep = NamedSharding(self.mesh, P())               # metrics: on every device, so every process reads them
        st = self._state_sharding
        each = jax.vmap if seeded else (lambda f: f)
        self.iteration = jit(each(self._iteration), out=(st, rep))
        self.rollout = jit(each(self._rollout), out=(st, bt, rep))
        self.update = jit(each(self._update), out=(st, rep))
        self.evaluate_windows = jit(each(self._evaluate_windows), out=None)
        self._init = jit(each(self._init_state), out=st)

    # ------------------------------------------------------------------ state
    def init(self, key: jax.Array) -> TrainState:
        """The initial train state (jitted: environment resets and parameter init compile into one program).
        With `seeds=S`, `key` holds S keys (`seed_keys`) and the state has a leading seed axis."""
        typed = jax.dtypes.issubdtype(jnp.asarray(key).dtype, jax.dtypes.prng_key)
        if self.num_seeds is not None and jnp.shape(key) != (self.num_seeds, *(() if typed else (2,))):
            raise ValueError(f"init: expected {self.num_seeds} keys (one per seed), got an array of shape "
                             f"{jnp.shape(key)}")
        return self._init(key)

    @property
    def num_devices(self) -> int:
        return 1 if self.mesh is None else self.mesh.size

    def place(self, ts: TrainState) -> TrainState:
        """A train state (a restored checkpoint, say) laid out over this trainer's devices."""
        return ts if self._state_sharding is None else jax.device_put(ts, self._state_sharding)

    def abstract_state(self) -> TrainState:
        """ONE run's train state: structure, shapes and dtypes (`jax.eval_shape` of the single-seed init), nothing
        computed. A checkpoint (always one seed's) is restored into it."""
        return jax.eval_shape(self._init_state, jax.random.PRNGKey(0))

    def _init_state(self, key: jax.Array) -> TrainState:
        cfg, env, model = self.cfg, self.env, self.model
        k_env, k_model, k_next = jax.random.split(key, 3)
        sampler = sampling.init(env.num_robots, cfg.sampling)
        env_state = env.init(k_env, cfg.num_envs, sampler)
        obs_rms = RunningMeanStd.create((env_state.obs.proprio[0].size,))
        obs = self._normalize(obs_rms, env_state.obs)
        params = model.init(k_model, env.robots, jax.tree.map(lambda x: x[:1], obs))
        opt_state = self.tx.init(params)
        carry = model.initial_carry(cfg.num_envs)
        b = cfg.burn_in
        return TrainState(
            params=params, opt_state=opt_state, obs_rms=obs_rms, rew=RewardScaler.create(cfg.num_envs),
            env=env_state, carry=carry, first=jnp.ones((cfg.num_envs,), bool),
            tail_obs=jax.tree.map(lambda x: jnp.broadcast_to(x, (b, *x.shape)), obs),
            tail_first=jnp.ones((b, cfg.num_envs), bool), tail_carry=carry, sampler=sampler, key=k_next,
            iteration=jnp.int32(0))

    _normalize = staticmethod(normalize_obs)

    # ------------------------------------------------------------------ rollout
    def _act(self, params, cache, sampler, c: ActCarry, key):
        env_state, carry, first, obs_rms, rew = c
        model, robots = self.model, self.env.robots
        obs_rms = obs_rms.update(env_state.obs.proprio.reshape(self.cfg.num_envs, -1))
        obs = self._normalize(obs_rms, env_state.obs)
        mu, value, carry = model.step(params, robots, obs, carry, first, cache=cache)
        act_mask = robots.act_mask[obs.robot]
        action = model.sample(key, mu, act_mask)
        logp = model.log_prob(mu, action, act_mask)
        nxt = self.env.vstep(env_state, action, sampler)
        rew, scaled = rew(nxt.reward, nxt.done, self.cfg.gamma)
        ep = nxt.ended
        tr = Transition(obs, first, action, logp, value, scaled, nxt.reward, nxt.done, nxt.truncated,
                        ep.ret, ep.length, ep.robot, ep.unstable, ep.fell)
        return ActCarry(nxt, carry, nxt.done, obs_rms, rew), tr

    def _rollout(self, ts: TrainState):
        cfg = self.cfg
        cache = self.model.robot_cache(ts.params, self.env.robots)
        key, k_roll = jax.random.split(ts.key)
        b, w = cfg.burn_in, cfg.window
        # The acting state at the rollout start is re-derived by the same burn-in over the tail that training will
        # run, with the current parameters: acting and training then see identical states (ratio exactly 1).
        carry = self.model.advance(ts.params, self.env.robots, ts.tail_obs, ts.tail_carry, ts.tail_first,
                                   cache=cache, batch_major=self.batch_major) if b else ts.carry
        c0 = ActCarry(ts.env, carry, ts.first, ts.obs_rms, ts.rew)
        keys = jax.random.split(k_roll, cfg.rollout_len).reshape(self.num_windows, cfg.window, -1)
        save_at = w - b if b else w          # the next window's burn-in starts after w - b steps of this one

        def act(c, x):                       # one body for every step, so the env step is compiled once
            i, k = x
            c, saved = c
            saved = jax.tree.map(lambda s, cur: jnp.where(i == save_at, cur, s), saved, c.carry)
            c, tr = self._act(ts.params, cache, ts.sampler, c, k)
            return (c, saved), tr

        def window(c, ks):                   # saved: the recurrent state where the next window's burn-in starts
            (c, saved), tr = jax.lax.scan(act, (c, c.carry), (jnp.arange(w), ks))
            return c, (tr, saved if b else c.carry)

        c, (tr, burn_starts) = jax.lax.scan(window, c0, keys)
        tr = jax.tree.map(lambda x: x.reshape(cfg.rollout_len, *x.shape[2:]), tr)   # (T, N, ...)
        env_state, carry, first, obs_rms, rew = c
        # V(s_T) with the live state (the state itself is not advanced: the next rollout redoes this step)
        last_obs = self._normalize(obs_rms, env_state.obs)
        _, last_value, _ = self.model.step(ts.params, self.env.robots, last_obs, carry, first, cache=cache)
        adv, ret = gae(tr.value, tr.reward, tr.done, tr.truncated, last_value, cfg.gamma, cfg.lam)
        adv = (adv - adv.mean()) / (adv.std(ddof=1) + 1e-5)
        starts = jax.tree.map(lambda t, s: jnp.concatenate([t[None], s[:-1]]), ts.tail_carry, burn_starts)
        batch = Batch(obs=jax.tree.map(lambda t, o: jnp.concatenate([t, o]), ts.tail_obs, tr.obs),
                      first=jnp.concatenate([ts.tail_first, tr.first]), starts=starts, action=tr.action,
                      logp=tr.logp, value=tr.value, adv=adv, ret=ret)
        t_total = cfg.rollout_len
        ts = ts.replace(
            env=env_state, carry=carry, first=first, obs_rms=obs_rms, rew=rew, key=key,
            tail_obs=jax.tree.map(lambda o: o[t_total - b:], tr.obs), tail_first=tr.first[t_total - b:],
            tail_carry=jax.tree.map(lambda s: s[-1], burn_starts),
            sampler=sampling.update(ts.sampler, tr.ep_length, tr.ep_robot, tr.done))
        return ts, batch, self._rollout_metrics(tr)

    @staticmethod
    def _rollout_metrics(tr: Transition) -> dict:
        done = tr.done.astype(jnp.float32)
        n = done.sum()
        mean = lambda x: jnp.where(n > 0, (x * done).sum() / jnp.maximum(n, 1), jnp.nan)
        return {"episode_return": mean(tr.ep_return), "episode_length": mean(tr.ep_length.astype(jnp.float32)),
                "episodes": n, "fall_fraction": mean(tr.fell.astype(jnp.float32)),
                "instabilities": (tr.unstable & tr.done).sum().astype(jnp.float32),
                "reward_mean": tr.raw_reward.mean(), "value_mean": tr.value.mean()}

    # ------------------------------------------------------------------ update
    def _minibatch(self, batch: Batch, ids: jax.Array) -> Minibatch:
        """Windows `ids` -> time-major sequences of B + W steps and their targets, M = G * m windows.
        `ids` (G, m): in each of the G equal blocks of envs, block-local windows j = k * (N / G) + n' (window k of the
        block's env n'). Each block is gathered from its own envs (vmap over the blocks), so where the envs are
        sharded over devices every device gathers and computes its own blocks' share of the minibatch."""
        cfg = self.cfg
        g, m = ids.shape
        per_block = cfg.num_envs // g
        k, n = ids // per_block, ids % per_block                                 # (G, m)
        b, w = cfg.burn_in, cfg.window
        t_seq = (k * w)[:, None, :] + jnp.arange(b + w)[None, :, None]          # (G, B + W, m) tail+rollout time
        t_win = t_seq[:, b:] - b                                                # (G, W, m) rollout time

        def blocked(x, t):          # x (time, N, ...), t (G, L, m) -> (L, G * m, ...): block i's from block i's envs
            xb = x.reshape(x.shape[0], g, per_block, *x.shape[2:])
            out = jax.vmap(lambda xg, tg, ng: xg[tg, ng[None, :]], in_axes=(1, 0, 0), out_axes=1)(xb, t, n)
            return out.reshape(out.shape[0], g * m, *out.shape[3:])

        obs = jax.tree.map(lambda x: blocked(x, t_seq), batch.obs)
        first = blocked(batch.first, t_seq)
        carry0 = jax.tree.map(lambda s: blocked(s, k[:, None])[0], batch.starts)     # s (K, N, ...): window k's start
        pick = lambda x: blocked(x, t_win)
        return Minibatch(obs, first, carry0, pick(batch.action), pick(batch.logp), pick(batch.value),
                         pick(batch.adv), pick(batch.ret))

    def _loss(self, params, batch: Batch, ids):
        mb = self._minibatch(batch, ids)
        model, robots = self.model, self.env.robots
        mu, value, _ = model.sequence(params, robots, mb.obs, mb.carry0, mb.first, burn_in=self.cfg.burn_in,
                                      batch_major=self.batch_major)
        act_mask = robots.act_mask[mb.obs.robot[self.cfg.burn_in:]]
        logp = model.log_prob(mu, mb.action, act_mask)
        info = ppo_loss(logp, mb.logp, mb.adv, value, mb.value, mb.ret, model.entropy(mu, act_mask),
                        clip_eps=self.cfg.clip_eps, value_coef=self.cfg.value_coef,
                        entropy_coef=self.cfg.entropy_coef)
        return info.loss, info

    def _evaluate_windows(self, params, batch: Batch):
        """(logp, value) recomputed for every window of `batch`, and the stored (logp_old, value_old), all
        (W, num_windows). With the rollout's parameters they must agree: the test of the recurrent bookkeeping."""
        ids = jnp.tile(jnp.arange(self.cfg.num_envs * self.num_windows // self.blocks), (self.blocks, 1))
        mb = self._minibatch(batch, ids)
        mu, value, _ = self.model.sequence(params, self.env.robots, mb.obs, mb.carry0, mb.first,
                                           burn_in=self.cfg.burn_in, batch_major=self.batch_major)
        logp = self.model.log_prob(mu, mb.action, self.env.robots.act_mask[mb.obs.robot[self.cfg.burn_in:]])
        return logp, value, mb.logp, mb.value

    def _update(self, ts: TrainState, batch: Batch):
        cfg = self.cfg
        lr = learning_rate(ts.iteration, self.num_iters, cfg.lr, cfg.warmup_iters)
        opt_state = ts.opt_state._replace(hyperparams={**ts.opt_state.hyperparams, "learning_rate": lr})
        key, k_perm = jax.random.split(ts.key)
        ids = shuffle_windows(k_perm, cfg.epochs, cfg.num_envs * self.num_windows, self.mb_windows, self.blocks)
        grad_fn = jax.value_and_grad(self._loss, has_aux=True)
        zero_info = LossInfo(*([jnp.float32(0.0)] * len(LossInfo._fields)))

        def running(c: SGDCarry):
            return (c.step < ids.shape[0]) & ~c.stopped

        def mb_step(c: SGDCarry) -> SGDCarry:
            (_, info), grads = grad_fn(c.params, batch, ids[c.step])
            ok = info.approx_kl <= cfg.kl_threshold
            updates, new_opt = self.tx.update(grads, c.opt_state, c.params)
            new_params = optax.apply_updates(c.params, updates)
            keep = lambda a, b: jax.tree.map(lambda x, y: jnp.where(ok, x, y), a, b)
            acc = jax.tree.map(lambda a, x: a + jnp.where(ok, x, 0.0), c.acc, info)
            # the first minibatch's statistics, applied or not (a rejected one is when wrong stored states show)
            first_info = jax.tree.map(lambda f, x: jnp.where(c.step == 0, x, f), c.first_info, info)
            return SGDCarry(c.step + 1, keep(new_params, c.params), keep(new_opt, c.opt_state), ~ok, acc,
                            c.applied + ok.astype(jnp.int32), first_info)

        c0 = SGDCarry(jnp.int32(0), ts.params, opt_state, jnp.asarray(False), zero_info, jnp.int32(0), zero_info)
        _, params, opt_state, _, acc, applied, first_info = jax.lax.while_loop(running, mb_step, c0)
        n = jnp.maximum(applied, 1).astype(jnp.float32)
        metrics = {f"{k}": v / n for k, v in acc._asdict().items()}
        metrics.update(lr=lr, minibatches=applied.astype(jnp.float32),
                       epochs_run=applied.astype(jnp.float32) / self.num_minibatches,
                       first_ratio=first_info.ratio_mean, first_kl=first_info.approx_kl)
        ts = ts.replace(params=params, opt_state=opt_state, key=key, iteration=ts.iteration + 1)
        return ts, metrics

    def _iteration(self, ts: TrainState):
        ts, batch, m1 = self._rollout(ts)
        ts, m2 = self._update(ts, batch)
        return ts, {**m1, **m2}


# ---------------------------------------------------------------------- several devices
def minibatch_blocks(cfg: PPOConfig, mb_windows: int, env_shards: int) -> int:
    """G of `ppo.minibatch_blocks` (None: the env shards), checked against the geometry and the devices."""
    g = env_shards if cfg.minibatch_blocks is None else int(cfg.minibatch_blocks)
    if cfg.num_envs % g or mb_windows % g or g % env_shards:
        raise ValueError(f"ppo.minibatch_blocks={g}: expected a divisor of ppo.num_envs={cfg.num_envs} and of the "
                         f"{mb_windows} windows of a minibatch, and a multiple of the {env_shards} device(s) the envs "
                         "are sharded over (each device gathers whole blocks)")
    return g


def shuffle_windows(key: jax.Array, epochs: int, n_windows: int, mb_windows: int, blocks: int) -> jax.Array:
    """The minibatches of every epoch, (epochs * minibatches, G, m) block-local window ids: each epoch a random
    permutation of each block's windows, minibatch i taking the i-th m = mb_windows / G of every block. G = 1 is the
    plain shuffle of all windows (flat ids k * N + n), without replacement within an epoch either way."""
    per_block, m = n_windows // blocks, mb_windows // blocks
    keys = jax.random.split(key, epochs)
    if blocks == 1:             # one permutation of all windows per epoch (the original PPO's shuffle)
        perms = jax.vmap(lambda k: jax.random.permutation(k, n_windows))(keys)[:, None]
    else:
        perms = jax.vmap(lambda k: jax.vmap(lambda kb: jax.random.permutation(kb, per_block))(
            jax.random.split(k, blocks)))(keys)                                  # (epochs, G, per_block)
    used = (n_windows // mb_windows) * m                                         # whole minibatches only
    ids = perms[:, :, :used].reshape(epochs, blocks, -1, m)                      # (epochs, G, minibatches, m)
    return ids.transpose(0, 2, 1, 3).reshape(-1, blocks, m)


def seed_keys(seeds) -> jax.Array:
    """The init keys of several seeds, stacked: `trainer.init(seed_keys([0, 1]))`."""
    return jnp.stack([jax.random.PRNGKey(int(s)) for s in seeds])


def seed_state(ts: TrainState, i: int) -> TrainState:
    """Seed i's train state out of a state with a leading seed axis (what its checkpoint holds)."""
    return jax.tree.map(lambda x: x[i], ts)


def stack_seeds(states) -> TrainState:
    """One state with a leading seed axis from single-seed states (restored checkpoints, say)."""
    return jax.tree.map(lambda *xs: jnp.stack(xs), *states)


def device_mesh(devices: int | None, num_envs: int, seeds: int | None = None) -> Mesh | None:
    """The mesh ("seed", "env") over the first `devices` devices (None: all visible ones); None for one device.
    With `seeds` runs side by side, gcd(seeds, devices) devices split the seeds (no communication between them)
    and each seed's envs are sharded over the rest; one run uses a seed axis of size 1. With several processes
    (mjx_morph/run/distributed.py) the devices are those of every process, an equal share of each: every process
    steps the envs of its own devices."""
    avail = jax.devices()
    procs = jax.process_count()
    n = len(avail) if devices is None else int(devices)
    if not 1 <= n <= len(avail):
        raise ValueError(f"devices={devices}: expected 1 to {len(avail)} (the visible {avail[0].platform} devices"
                         + (f" of {procs} processes" if procs > 1 else "") + ") or null for all")
    if n % procs:
        raise ValueError(f"devices={devices}: expected a multiple of the {procs} processes (each process steps the "
                         "envs of an equal share of the devices) or null for all")
    if n == 1:
        return None
    by_seed = math.gcd(seeds or 1, n)
    by_env = n // by_seed
    if num_envs % by_env:
        raise ValueError(f"ppo.num_envs={num_envs} is not a multiple of {by_env}, the devices each run's envs are "
                         f"spread over (devices={n}" + (f", seeds={seeds}" if seeds else "")
                         + (f", {procs} processes" if procs > 1 else "") + "): each device steps an equal share of "
                         "the envs")
    if procs > 1:
        per = n // procs
        avail = [d for p in range(procs) for d in [d for d in avail if d.process_index == p][:per]]
    return Mesh(np.asarray(avail[:n]).reshape(by_seed, by_env), ("seed", "env"))


def state_sharding(mesh: Mesh, seeded: bool = False) -> TrainState:
    """Shardings of a train state, one per field (a tree prefix: it applies to every array of the field): env-axis
    fields over "env" (axis 0, or axis 1 for the time-major tails), the rest replicated; with `seeded`, every field's
    leading seed axis over "seed"."""
    lead = ("seed",) if seeded else ()
    env0, env1, rep = (NamedSharding(mesh, P(*lead, *spec)) for spec in (("env",), (None, "env"), ()))
    return TrainState(params=rep, opt_state=rep, obs_rms=rep, rew=RewardScaler(returns=env0, stats=rep), env=env0,
                      carry=env0, first=env0, tail_obs=env1, tail_first=env1, tail_carry=env0, sampler=rep, key=rep,
                      iteration=rep)
