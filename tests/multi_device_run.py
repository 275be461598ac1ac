"""Run by tests/test_devices.py in a fresh process with N virtual CPU devices (XLA_FLAGS must be set before JAX
starts): train the same tiny config on 1 device and on N devices and print how far apart they end, as JSON."""
from __future__ import annotations

import json
import re
import sys

import jax
import numpy as np

from mjx_morph.nets import make_model
from mjx_morph.ppo.config import PPOConfig
from mjx_morph.ppo.trainer import Trainer, seed_keys, seed_state
from toy_env import ToyEnv

TINY = dict(d_model=16, num_layers=1, num_heads=2, ffn_dim=32)


def ppo_config(blocks: int | None = None) -> PPOConfig:
    return PPOConfig(num_envs=8, rollout_len=16, window=8, burn_in=4, minibatch_size=32, epochs=2,
                     minibatch_blocks=blocks)


def toy_trainer(arch: str, devices: int | None, total_steps: int = 8 * 16 * 10, seeds: int | None = None,
                blocks: int | None = None) -> Trainer:
    """The tiny config on the ToyEnv (also tests/multi_process_run.py and tests/test_multihost.py)."""
    model = make_model(arch, hfield=False, decoder_dims=[], precision="fp32", **TINY)
    return Trainer(ToyEnv(), model, ppo_config(blocks), total_steps, fast_compile=True, devices=devices,
                   seeds=seeds)


def iteration(trainer: Trainer, ts):
    """One iteration as a run takes it by default (`phase_timing`): the rollout and the update, two jitted calls.
    -> (state, metrics, the rollout's batch)."""
    ts, batch, m1 = trainer.rollout(ts)
    ts, m2 = trainer.update(ts, batch)
    return ts, {**m1, **m2}, batch


def update_collectives(trainer: Trainer, ts, batch) -> list[list]:
    """[op, elements] of every collective in the compiled update (the minibatch loop) of `trainer`, lowered for a
    state and batch like those it has run on (its program is then compiled already: lowering it again is free)."""
    out = []
    for line in trainer.update.lower(ts, batch).compile().as_text().splitlines():
        m = re.search(r"= (.*?) (all-gather|all-reduce|all-to-all|collective-permute|reduce-scatter)(-start)?\(", line)
        if m:
            sizes = [int(np.prod([int(d) for d in dims.split(",") if d])) for dims in re.findall(r"\[([\d,]*)\]",
                                                                                                   m.group(1))]
            out.append([m.group(2), sum(sizes)])
    return out


def run(arch: str, devices: int, iters: int = 3, seed: int = 0, blocks: int | None = None,
        trainer: Trainer | None = None):
    """`iters` iterations of the tiny config from `seed`; pass `trainer` (one of `toy_trainer(arch, devices,
    blocks=blocks)`) to reuse its compiled functions instead of tracing and loading them again."""
    trainer = trainer or toy_trainer(arch, devices, blocks=blocks)
    ts = trainer.init(jax.random.PRNGKey(seed))
    rows = []
    for _ in range(iters):
        ts, m, batch = iteration(trainer, ts)
        rows.append({k: float(v) for k, v in m.items()})
    shards = len(ts.carry["actor"]["h"].sharding.device_set) if trainer.model.recurrent else \
        len(ts.first.sharding.device_set)
    return ts, rows, shards, trainer, batch


def main(n: int) -> None:
    assert len(jax.devices()) == n, jax.devices()
    out = {}
    for arch in ("rmomo", "metamorph"):
        one, rows1, s1, one_trainer, _ = run(arch, 1, blocks=n)   # the minibatches of n devices: n blocks of envs
        many, rows_n, s_n, many_trainer, batch = run(arch, n)
        diff = max(float(np.abs(np.asarray(a) - np.asarray(b)).max())
                   for a, b in zip(jax.tree.leaves(one.params), jax.tree.leaves(many.params)))
        env_diff = float(np.abs(np.asarray(one.env.obs.proprio) - np.asarray(many.env.obs.proprio)).max())
        out[arch] = {"param_diff": diff, "env_diff": env_diff, "shards": [s1, s_n],
                     "minibatches": [r["minibatches"] for r in rows1], "minibatches_n": [r["minibatches"] for r in rows_n],
                     "loss": [r["loss"] for r in rows1], "loss_n": [r["loss"] for r in rows_n],
                     "collectives": update_collectives(many_trainer, many, batch),
                     "params": int(sum(np.size(x) for x in jax.tree.leaves(many.params))),
                     "tables": int(sum(np.prod(x.shape) for x in jax.tree.leaves(jax.eval_shape(
                         one_trainer.model.robot_cache, one.params, one_trainer.env.robots))))}
        if arch == "metamorph":      # two seeds side by side, spread over the devices (a 2 x n/2 mesh)
            trainer = toy_trainer(arch, n, seeds=2, blocks=n)
            ts = trainer.init(seed_keys([0, 1]))
            for _ in range(3):
                ts, _, _ = iteration(trainer, ts)
            alone = [one, run(arch, 1, seed=1, blocks=n, trainer=one_trainer)[0]]     # the same 1-device program
            out["seeds"] = {"mesh": dict(trainer.mesh.shape), "shards": len(ts.first.sharding.device_set),
                            "param_diff": max(float(np.abs(np.asarray(a) - np.asarray(b)).max())
                                              for i in range(2) for a, b in
                                              zip(jax.tree.leaves(seed_state(ts, i).params),
                                                  jax.tree.leaves(alone[i].params)))}
    print(json.dumps(out))


if __name__ == "__main__":
    main(int(sys.argv[1]))
