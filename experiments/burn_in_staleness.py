"""How stale is the acting state that the burn-in re-derives after a PPO update?

    python -m experiments.burn_in_staleness robots=gen/train preset=smoke
    python -m experiments.burn_in_staleness robots=gen/train preset=smoke arch=rmemo lengths=[0,20,50,100,200] \
        history=400 pretrain_iters=5

A rollout acts from the state re-derived by a burn-in of B = ppo.burn_in steps with the NEW parameters, started
from the state stored B steps before the previous rollout's end, which the OLD parameters computed. The true state
under the new parameters would replay each episode from its start. This measures the gap for several burn-in
lengths L, after one update:

1. `pretrain_iters` ordinary iterations, then rollouts with no update between them until `history` steps per env
   are recorded (all under one parameter set p0; their live state is exact under p0, which
   tests/test_ppo_bookkeeping.py checks and which is checked here again).
2. One PPO update on the last of these rollouts: p1.
3. For each L: the p0 state L steps before the end, advanced over the last L recorded observations with p1.
   L = 0 is the live p0 state itself. The reference is the burn-in over the whole history from its start state;
   with pretrain_iters=0 the history starts with the training (zero states, every episode starting), so the
   reference is the exact p1 state.

Printed per L against the reference: the relative difference of the states (every cell's h and c, real limbs), of
the policy means and values for the next observation, the mean KL between the two policies there, the mean |log-prob
difference| of actions drawn from the reference policy, and the fraction of envs whose episode began before the
burn-in's start (only those can differ). "update" is the update's own effect (p0 with its live state against the
reference), for scale.
"""
from __future__ import annotations

import dataclasses
import math
import sys
from typing import Any, List, Optional

import jax
import jax.numpy as jnp
import numpy as np

from mjx_morph.nets import distribution
from mjx_morph.ppo.trainer import Trainer, TrainState, normalize_obs
from mjx_morph.run import RunConfig, build, register

from . import cli


@dataclasses.dataclass
class StalenessConfig(RunConfig):
    lengths: List[int] = dataclasses.field(default_factory=lambda: [0, 20, 50, 100, 200])   # burn-in lengths L
    history: Optional[int] = None       # steps recorded per env before the update (rounded up to whole rollouts);
                                        # None: 2 x max(lengths)
    pretrain_iters: int = 0             # ordinary training iterations first (0: the reference is the exact state)
    action_samples: int = 64            # actions drawn per env from the reference policy for the log-prob column


register("burn_in_staleness_schema", StalenessConfig)


def record(trainer: Trainer, ts: TrainState, steps: int):
    """Rollouts with no update between them until `steps` steps per env are recorded.

    -> (train state after them, the last rollout's batch, normalised observations (H, N, ...), episode-start flags
    (H, N), the state the first recorded step acted from)."""
    b = trainer.cfg.burn_in
    start = ts.carry
    if b:
        start = trainer.model.advance(ts.params, trainer.env.robots, ts.tail_obs, ts.tail_carry, ts.tail_first)
    obs, first = [], []
    for _ in range(math.ceil(steps / trainer.cfg.rollout_len)):
        ts, batch, _ = trainer.rollout(ts)
        obs.append(jax.tree.map(lambda x: x[b:], batch.obs))
        first.append(batch.first[b:])
    return ts, batch, jax.tree.map(lambda *x: jnp.concatenate(x), *obs), jnp.concatenate(first), start


def _burn_in_states(model, robots, p_old, p_new, obs, first, start, switch):
    """States after the whole of `obs` (H, N, ...) from `start`, one per entry of `switch` (M,): steps t < switch[m]
    run with `p_old`, the later ones with `p_new`. -> carry with leaves (M, N, ...)."""
    m = switch.shape[0]
    n = first.shape[1]
    cache_old, cache_new = model.robot_cache(p_old, robots), model.robot_cache(p_new, robots)
    tile = lambda x: jnp.broadcast_to(x[None], (m, *x.shape)).reshape(m * n, *x.shape[1:])   # noqa: E731
    carry = jax.tree.map(tile, start)

    def body(carry, x):
        o, f, t = x
        o, f = jax.tree.map(lambda y: tile(y)[None], o), tile(f)[None]
        old = model.advance(p_old, robots, o, carry, f, cache=cache_old)
        new = model.advance(p_new, robots, o, carry, f, cache=cache_new)
        use_new = jnp.repeat(t >= switch, n)
        return jax.tree.map(lambda a, b: jnp.where(use_new.reshape(-1, *[1] * (a.ndim - 1)), b, a), old, new), None

    carry, _ = jax.lax.scan(body, carry, (obs, first, jnp.arange(first.shape[0])))
    return jax.tree.map(lambda x: x.reshape(m, n, *x.shape[1:]), carry)


def staleness(trainer: Trainer, ts: TrainState, lengths: List[int], history: Optional[int] = None,
              action_samples: int = 64, seed: int = 0) -> dict[str, Any]:
    """Measure (see the module docstring) from train state `ts`; -> dict of per-length lists and scalars."""
    model, robots = trainer.model, trainer.env.robots
    if not model.recurrent:
        raise ValueError(f"{model.arch} is feed-forward: it has no recurrent state to go stale")
    lengths = sorted(int(x) for x in lengths)
    if lengths[0] < 0:
        raise ValueError(f"lengths={lengths}: expected burn-in lengths >= 0")
    history = 2 * lengths[-1] if history is None else int(history)
    ts, batch, obs, first, start = record(trainer, ts, max(history, lengths[-1], 1))
    h = first.shape[0]
    p0 = ts.params
    ts1, _ = trainer.update(ts, batch)
    p1 = ts1.params
    # the observation the next rollout acts on first, normalised as the rollout would
    env_obs = ts.env.obs
    nxt = normalize_obs(ts.obs_rms.update(env_obs.proprio.reshape(env_obs.proprio.shape[0], -1)), env_obs)
    # switch times: reference (all steps with p1), each L (p1 for the last L steps), p0 throughout (the live state)
    switch = jnp.asarray([0, *[h - L for L in lengths], h], jnp.int32)
    states = jax.jit(_burn_in_states, static_argnums=0)(model, robots, p0, p1, obs, first, start, switch)
    at = lambda i: jax.tree.map(lambda x: x[i], states)                      # noqa: E731
    live_check = max(float(jnp.abs(a - b).max()) for a, b in zip(jax.tree.leaves(at(-1)), jax.tree.leaves(ts.carry)))

    step = jax.jit(model.step)
    act_mask = robots.act_mask[nxt.robot]
    node = np.asarray(robots.node_mask[nxt.robot])
    mu_ref, v_ref, _ = step(p1, robots, nxt, at(0), ts.first)
    key = jax.random.PRNGKey(seed)
    actions = model.sample(key, jnp.broadcast_to(mu_ref, (action_samples, *mu_ref.shape)), act_mask)
    logp_ref = model.log_prob(mu_ref, actions, act_mask)

    def leaves(c):
        return [np.asarray(x)[node] for x in jax.tree.leaves(c)]            # real limbs only

    def rel(a, b):
        return float(np.sqrt(sum(np.sum((x - y) ** 2) for x, y in zip(a, b)) / sum(np.sum(y ** 2) for y in b)))

    def policy_gap(mu, v):
        kl = distribution.kl_divergence(mu_ref, mu, act_mask, model.action_std)
        dlogp = jnp.abs(model.log_prob(mu, actions, act_mask) - logp_ref)
        return (rel([np.asarray(mu)], [np.asarray(mu_ref)]), rel([np.asarray(v)], [np.asarray(v_ref)]),
                float(kl.mean()), float(dlogp.mean()))

    ref_leaves = leaves(at(0))
    out: dict[str, Any] = {"arch": model.arch, "history": h, "num_envs": int(first.shape[1]), "lengths": lengths,
                           "state_rel": [], "mu_rel": [], "value_rel": [], "kl": [], "abs_dlogp": [],
                           "stale_envs": [], "live_check": live_check}
    for i, L in enumerate(lengths):
        s = at(i + 1)
        mu, v, _ = step(p1, robots, nxt, s, ts.first)
        mu_rel, v_rel, kl, dlogp = policy_gap(mu, v)
        out["state_rel"].append(rel(leaves(s), ref_leaves))
        out["mu_rel"].append(mu_rel)
        out["value_rel"].append(v_rel)
        out["kl"].append(kl)
        out["abs_dlogp"].append(dlogp)
        # envs whose episode began before the burn-in's start (no reset in its L steps nor at the next step)
        began = ~np.asarray(first[h - L:]).any(0) & ~np.asarray(ts.first)
        out["stale_envs"].append(float(began.mean()))
    mu0, v0, _ = step(p0, robots, nxt, ts.carry, ts.first)
    out["update"] = dict(zip(("mu_rel", "value_rel", "kl", "abs_dlogp"), policy_gap(mu0, v0)))
    return out


def format_table(r: dict[str, Any]) -> str:
    """The measurement as a plain-text table."""
    lines = [f"# {r['arch']}: {r['num_envs']} envs, {r['history']} recorded steps, one update; reference: burn-in "
             f"over all {r['history']} steps (live-state check {r['live_check']:.1e})",
             f"{'burn_in':>8} {'state_rel':>10} {'mu_rel':>10} {'value_rel':>10} {'kl':>10} {'|dlogp|':>10} "
             f"{'stale_envs':>10}"]
    for i, L in enumerate(r["lengths"]):
        lines.append(f"{L:>8} {r['state_rel'][i]:>10.2e} {r['mu_rel'][i]:>10.2e} {r['value_rel'][i]:>10.2e} "
                     f"{r['kl'][i]:>10.2e} {r['abs_dlogp'][i]:>10.2e} {r['stale_envs'][i]:>10.2f}")
    u = r["update"]
    lines.append(f"{'update':>8} {'':>10} {u['mu_rel']:>10.2e} {u['value_rel']:>10.2e} {u['kl']:>10.2e} "
                 f"{u['abs_dlogp']:>10.2e}")
    return "\n".join(lines)


def run(cfg: StalenessConfig) -> None:
    exp = build(cfg)
    trainer = exp.trainer
    ts = trainer.init(jax.random.PRNGKey(cfg.seed))
    for _ in range(cfg.pretrain_iters):
        ts, _ = trainer.iteration(ts)
    print(format_table(staleness(trainer, ts, cfg.lengths, cfg.history, cfg.action_samples, cfg.seed)), flush=True)


def main(argv=None) -> int:
    return cli.main(run, "burn_in_staleness", StalenessConfig, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
