"""Actor + critic behind one interface for acting (one step) and training (a sequence with burn-in).

Inputs: `Robots` (constant per robot) and `Obs` (per env or sample, any leading batch shape, proprio already
normalised), both defined in `mjx_morph.layout`; plain dicts with the `Obs` keys are accepted too.

How the previous action enters (the models that use it: rmemo, rmomo, grumomo, hyperrmomo): the model clips
it to [-1, 1] (the control MuJoCo executes; `clip_prev_action`), zeroes the entries with act_mask False and
zeroes all of it where `reset` is True, so a stale action never leaks into a new episode even if the caller
forgot to clear it. Limb l reads entries (2l, 2l+1).

Carry: {"actor": state, "critic": state}, state = {"h", "c"} (LSTM) or {"h"} (GRU), each [..., 12, H];
the feed-forward architectures carry `{}` so the PPO code is the same for all. A state is zeroed where
`reset` is True before it is used, and kept at zero on padded limbs.

Per-robot work (`robot_cache`) is computed once per call for the R robots and gathered by `obs.robot`;
during a rollout the parameters do not change, so compute it once per rollout and pass `cache=` to `step`.

Training: `sequence` runs the per-limb embedding for all T*B samples at once, the cell as a `lax.scan` over
time (its input projection hoisted out of the scan), and the transformer + decoder once over all
(T - burn_in) * B window samples. The burn-in steps only advance the cell, under `stop_gradient`.

Arithmetic: `net.precision` (fp32 | tf32 | bf16, precision.py). Every public method traces the networks under it;
whatever it is, the carries and the outputs (mu, value) are float32.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Any, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from ..layout import (ACTS_PER_TOKEN, CTX_DIM, HFIELD_DIM, NUM_ACTIONS, NUM_TOKENS, OBS_DIM, STATE_FEATURES, Obs,
                      Robots)
from . import distribution, precision
from .network import NetConfig, PolicyNet
from .recurrent import zero_state

Params = dict
Carry = dict


def as_obs(obs: Any) -> Obs:
    if isinstance(obs, Obs):
        return obs
    if isinstance(obs, Mapping):
        return Obs(obs["proprio"], obs["prev_action"], obs["robot"], obs.get("hfield"))
    return Obs(obs.proprio, obs.prev_action, obs.robot, getattr(obs, "hfield", None))


def _in_precision(method):
    """Trace the method's network calls under the model's precision (precision.scope)."""
    @functools.wraps(method)
    def wrapped(self, *args, **kwargs):
        with precision.scope(self.net.precision):
            return method(self, *args, **kwargs)
    return wrapped


def _row_order(batch_major: bool):
    """[T, B, ...] <-> the order in which the per-sample networks see a sequence's rows: batch-major swaps the two
    leading axes (where B is sharded over devices a T*B merge with B minor cannot stay sharded), else nothing."""
    return (lambda x: jnp.swapaxes(x, 0, 1)) if batch_major else (lambda x: x)


def _flatten(tree: Any, n_lead: int) -> Any:
    """Merge the first n_lead axes of every leaf."""
    return jax.tree.map(lambda x: x.reshape((-1, *x.shape[n_lead:])), tree)


@dataclasses.dataclass(frozen=True, eq=False)
class Model:
    """An architecture of the zoo: two `PolicyNet`s (actor, critic) plus the acting/training interface."""
    arch: str
    net: NetConfig
    action_std: float = distribution.ACTION_STD
    clip_prev_action: bool = True
    clone_layer_init: bool = True   # PyTorch's TransformerEncoder deep-copies one layer: equal initial layers
    scan_unroll: int = 4            # time steps of the recurrent cell per iteration of its scan (speed only:
                                    # 4 made the R-MoMo update 9% faster on an H100 than 1, 10 no faster than 4)

    def __post_init__(self):
        object.__setattr__(self, "nets", {"actor": PolicyNet(self.net, ACTS_PER_TOKEN),
                                          "critic": PolicyNet(self.net, 1)})

    @property
    def recurrent(self) -> bool:
        return self.net.recurrent

    # ------------------------------------------------------------------ inputs
    def _parts(self, robots: Robots, obs: Obs, reset: jax.Array | None) -> dict:
        """Per-sample inputs with the leading batch axes of `obs.robot`."""
        idx = jnp.asarray(obs.robot, jnp.int32)
        act_mask = jnp.take(robots.act_mask, idx, axis=0)
        pa = jnp.asarray(obs.prev_action, jnp.float32)
        if self.clip_prev_action:
            pa = jnp.clip(pa, -1.0, 1.0)
        keep = act_mask if reset is None else act_mask & ~jnp.asarray(reset, bool)[..., None]
        pa = jnp.where(keep, pa, 0.0)
        proprio = jnp.asarray(obs.proprio, jnp.float32)
        parts = {
            "proprio": proprio,
            "state": proprio[..., STATE_FEATURES],
            "prev_action": pa.reshape(*pa.shape[:-1], NUM_TOKENS, ACTS_PER_TOKEN),
            "node_mask": jnp.take(robots.node_mask, idx, axis=0),
            "act_mask": act_mask,
            "robot": idx,
        }
        if self.net.hfield:
            if obs.hfield is None or jnp.shape(obs.hfield)[-1] != self.net.hfield_size:
                raise ValueError(f"{self.arch} was built with hfield=True but the observation has no "
                                 f"{self.net.hfield_size}-value 'hfield'")
            parts["hfield"] = jnp.asarray(obs.hfield, jnp.float32)
        return parts

    def _outputs(self, actor_out: jax.Array, critic_out: jax.Array, parts: dict) -> tuple[jax.Array, jax.Array]:
        """Per-limb outputs [N,12,2], [N,12,1] -> mu [N,24] (0 on masked entries), value [N] (mean over real limbs)."""
        actor_out, critic_out = actor_out.astype(jnp.float32), critic_out.astype(jnp.float32)
        mu = jnp.where(parts["act_mask"], actor_out.reshape(actor_out.shape[0], NUM_ACTIONS), 0.0)
        m = parts["node_mask"]
        v = jnp.sum(jnp.where(m, critic_out[..., 0], 0.0), axis=-1)
        value = v / jnp.maximum(jnp.sum(m, axis=-1), 1)
        return mu, value

    # ------------------------------------------------------------------ parameters
    @_in_precision
    def init(self, key: jax.Array, robots: Robots, obs_example: Any) -> Params:
        """Parameters {'actor': ..., 'critic': ...} (separately initialised networks)."""
        obs = as_obs(obs_example)
        n_lead = jnp.ndim(obs.robot)
        parts = _flatten(self._parts(robots, obs, None), n_lead) if n_lead else \
            _flatten(self._parts(robots, jax.tree.map(lambda x: x[None], obs), None), 1)
        params = {}
        for (name, net), k in zip(self.nets.items(), jax.random.split(key)):
            p = net.init(k, robots.context, robots.node_mask, parts)["params"]
            if self.clone_layer_init:
                p = {**p, **{f"layers_{i}": p["layers_0"] for i in range(1, self.net.num_layers)}}
            params[name] = p
        return params

    def num_params(self, params: Params | None = None) -> int:
        """Trainable parameters (from `params`, or from an abstract `init` via jax.eval_shape)."""
        if params is None:
            params = jax.eval_shape(self.init, jax.random.key(0), example_robots(), example_obs(self, (1,)))
        return int(sum(np.prod(x.shape) for x in jax.tree.leaves(params)))

    # ------------------------------------------------------------------ carries
    def initial_carry(self, batch_shape: int | tuple[int, ...]) -> Carry:
        if not self.recurrent:
            return {}
        shape = (batch_shape,) if isinstance(batch_shape, int) else tuple(batch_shape)
        return {name: zero_state(self.net.cell, (*shape, NUM_TOKENS), self.net.d_model) for name in self.nets}

    # ------------------------------------------------------------------ per robot
    @_in_precision
    def robot_cache(self, params: Params, robots: Robots) -> dict:
        """Per-robot quantities of both networks (hypernetwork outputs, fixed-attention probabilities, ...)."""
        return {name: net.apply({"params": params[name]}, robots.context, robots.node_mask, method="robot_cache")
                for name, net in self.nets.items()}

    # ------------------------------------------------------------------ acting
    @_in_precision
    def step(self, params: Params, robots: Robots, obs: Any, carry: Carry, reset: jax.Array,
             cache: dict | None = None) -> tuple[jax.Array, jax.Array, Carry]:
        """One step for a batch of envs: -> mu [*B, 24], value [*B], new carry.

        `reset` [*B] bool marks episode starts: the carry and the previous action are zeroed there first."""
        obs = as_obs(obs)
        reset = jnp.asarray(reset, bool)
        batch = reset.shape
        if cache is None:
            cache = self.robot_cache(params, robots)
        parts = _flatten(self._parts(robots, obs, reset), len(batch))
        flat_reset = reset.reshape(-1)
        outs, new_carry = {}, {}
        for name, net in self.nets.items():
            variables = {"params": params[name]}
            pre = net.apply(variables, parts, cache[name], method="pre")
            h = None
            if self.recurrent:
                state = jax.tree.map(lambda s: jnp.where(flat_reset[:, None, None], 0.0,
                                                         s.reshape(-1, *s.shape[len(batch):])), carry[name])
                state, h = net.apply(variables, state, pre["xg"], parts["node_mask"], method="recur")
                new_carry[name] = jax.tree.map(lambda s: s.reshape(*batch, *s.shape[1:]), state)
            outs[name] = net.apply(variables, pre, h, parts, cache[name], method="post")
        mu, value = self._outputs(outs["actor"], outs["critic"], parts)
        return mu.reshape(*batch, NUM_ACTIONS), value.reshape(batch), new_carry

    # ------------------------------------------------------------------ training
    def _scan(self, params: Params, carry: Carry, xg: dict, resets: jax.Array, node_mask: jax.Array):
        """The cells of both networks over time: xg[name] [T,B,12,G], resets [T,B], node_mask [T,B,12]."""
        def body(c, inp):
            xg_t, r_t, m_t = inp
            new, hs = {}, {}
            for name, net in self.nets.items():
                state = jax.tree.map(lambda s: jnp.where(r_t[:, None, None], 0.0, s), c[name])
                new[name], hs[name] = net.apply({"params": params[name]}, state, xg_t[name], m_t, method="recur")
            return new, hs
        return jax.lax.scan(body, carry, (xg, resets, node_mask), unroll=self.scan_unroll)

    @_in_precision
    def sequence(self, params: Params, robots: Robots, obs_seq: Any, carry0: Carry, resets: jax.Array,
                 burn_in: int = 0, cache: dict | None = None,
                 batch_major: bool = False) -> tuple[jax.Array, jax.Array, Carry]:
        """A sequence [T, B, ...] from stored start states `carry0` ([B, 12, H] leaves).

        -> mu [T - burn_in, B, 24], value [T - burn_in, B], carry after the last step. The first `burn_in`
        steps only advance the cells (no gradient flows through them); `resets[t]` zeroes the carry and the
        previous action before step t. With burn_in = 0 this equals T calls of `step`.
        `batch_major`: the per-sample networks see the window's samples in (B, T) order instead of (T, B), the same
        numbers in another row order; where B is sharded over devices this keeps it sharded (a (T, B) -> T*B merge
        with B minor cannot be, and XLA gathers the whole batch onto every device instead)."""
        obs_seq = as_obs(obs_seq)
        resets = jnp.asarray(resets, bool)
        t_all, b = resets.shape
        burn_in = int(burn_in)
        if not 0 <= burn_in <= t_all:
            raise ValueError(f"burn_in {burn_in} outside [0, {t_all}]")
        w = t_all - burn_in
        if cache is None:
            cache = self.robot_cache(params, robots)
        parts = self._parts(robots, obs_seq, resets)                     # [T, B, ...]
        order = _row_order(batch_major)
        win = _flatten(jax.tree.map(lambda x: order(x[burn_in:]), parts), 2)  # [W*B, ...] ([B*W, ...] batch-major)
        rows = (b, w) if batch_major else (w, b)
        outs = {}
        if not self.recurrent:
            for name, net in self.nets.items():
                variables = {"params": params[name]}
                pre = net.apply(variables, win, cache[name], method="pre")
                outs[name] = net.apply(variables, pre, None, win, cache[name], method="post")
            final = {}
        else:
            pre_w = {name: net.apply({"params": params[name]}, win, cache[name], method="pre")
                     for name, net in self.nets.items()}
            carry = carry0
            if burn_in:
                burn = jax.tree.map(lambda x: x[:burn_in], parts)
                carry = self._advance(params, burn, carry0, resets[:burn_in], cache, batch_major)
            xg_w = {name: order(p["xg"].reshape(*rows, NUM_TOKENS, -1)) for name, p in pre_w.items()}
            final, hs = self._scan(params, carry, xg_w, resets[burn_in:], parts["node_mask"][burn_in:])
            for name, net in self.nets.items():
                h = order(hs[name]).reshape(w * b, NUM_TOKENS, -1)
                outs[name] = net.apply({"params": params[name]}, pre_w[name], h, win, cache[name], method="post")
        mu, value = self._outputs(outs["actor"], outs["critic"], win)
        return order(mu.reshape(*rows, NUM_ACTIONS)), order(value.reshape(rows)), final

    def _advance(self, params: Params, parts: dict, carry0: Carry, resets: jax.Array, cache: dict,
                 batch_major: bool = False) -> Carry:
        """The cells alone over time-major `parts` [T, B, ...], under stop_gradient (the burn-in);
        `batch_major` as in `sequence`."""
        t, b = resets.shape
        order = _row_order(batch_major)
        rows = (b, t) if batch_major else (t, b)
        flat = _flatten(jax.tree.map(order, parts), 2)
        xg = {name: order(jax.lax.stop_gradient(
                  net.apply({"params": params[name]}, flat, cache[name], method="pre")["xg"]
              ).reshape(*rows, NUM_TOKENS, -1)) for name, net in self.nets.items()}
        carry, _ = self._scan(params, carry0, xg, resets, parts["node_mask"])
        return jax.lax.stop_gradient(carry)

    @_in_precision
    def advance(self, params: Params, robots: Robots, obs_seq: Any, carry0: Carry, resets: jax.Array,
                cache: dict | None = None, batch_major: bool = False) -> Carry:
        """Run only the recurrent cells over a sequence [T, B, ...] from `carry0` -- exactly the burn-in of
        `sequence` -- and return the carry after it (no outputs, no gradient). Feed-forward: returns carry0."""
        if not self.recurrent:
            return carry0
        obs_seq = as_obs(obs_seq)
        resets = jnp.asarray(resets, bool)
        if cache is None:
            cache = self.robot_cache(params, robots)
        return self._advance(params, self._parts(robots, obs_seq, resets), carry0, resets, cache, batch_major)

    # ------------------------------------------------------------------ distribution helpers
    def sample(self, key: jax.Array, mu: jax.Array, act_mask: jax.Array | None = None) -> jax.Array:
        return distribution.sample(key, mu, self.action_std, act_mask)

    def log_prob(self, mu: jax.Array, action: jax.Array, act_mask: jax.Array) -> jax.Array:
        return distribution.log_prob(mu, action, act_mask, self.action_std)

    def entropy(self, mu: jax.Array, act_mask: jax.Array) -> jax.Array:
        return distribution.entropy(mu, act_mask, self.action_std)


# ---------------------------------------------------------------------- examples (init / counting / tests)
def example_robots(num_robots: int = 1, num_limbs: int = NUM_TOKENS) -> Robots:
    """Zero-context robots whose first `num_limbs` tokens are real and whose real limbs have both joints."""
    node = np.arange(NUM_TOKENS) < num_limbs
    act = np.repeat(node, ACTS_PER_TOKEN)
    act[:ACTS_PER_TOKEN] = False  # the torso has no actuator
    return Robots(jnp.zeros((num_robots, NUM_TOKENS, CTX_DIM), jnp.float32),
                  jnp.asarray(np.broadcast_to(node, (num_robots, NUM_TOKENS))),
                  jnp.asarray(np.broadcast_to(act, (num_robots, NUM_ACTIONS))))


def example_obs(model: Model | None, batch_shape: tuple[int, ...] = (1,), hfield: bool | None = None) -> Obs:
    """An all-zero observation of the given batch shape (robot 0)."""
    if hfield is None:
        hfield = bool(model is not None and model.net.hfield)
    size = model.net.hfield_size if model is not None else HFIELD_DIM
    return Obs(jnp.zeros((*batch_shape, NUM_TOKENS, OBS_DIM), jnp.float32),
               jnp.zeros((*batch_shape, NUM_ACTIONS), jnp.float32),
               jnp.zeros(batch_shape, jnp.int32),
               jnp.zeros((*batch_shape, size), jnp.float32) if hfield else None)
