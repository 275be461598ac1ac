"""Training throughput: `python -m experiments.bench_train env=ft arch=rmomo` prints one JSON line.

Env steps per second end to end and per phase (rollout: physics + acting; update: GAE, all PPO epochs and
minibatches that the KL stop lets run), the mean number of epochs run, compile times and peak device memory.
After one warm-up iteration (compilation), `bench_iters` iterations are timed with the two phases as separate
jitted calls, then (fused=true) the same number as the single fused jitted iteration.
"""
from __future__ import annotations

import dataclasses
import json
import sys
import time
from typing import Optional

import jax
import numpy as np

from mjx_morph.run import RunConfig, build, register

from . import cli


@dataclasses.dataclass
class BenchTrainConfig(RunConfig):
    bench_iters: int = 4                    # timed iterations per phase, after one warm-up iteration (compilation)
    fused: bool = True                      # also time the fused one-jit iteration
    compile_cache: Optional[str] = None     # benchmarks measure compilation: never from the cache


register("bench_train_schema", BenchTrainConfig)


def _memory_gb() -> float:
    stats = jax.devices()[0].memory_stats() or {}
    return stats.get("peak_bytes_in_use", float("nan")) / 1e9


def note(text: str) -> None:
    """Progress on stderr, so that stdout stays one JSON line per case."""
    print(f"[bench_train] {text}", file=sys.stderr, flush=True)


def bench(cfg: BenchTrainConfig) -> None:
    t0 = time.perf_counter()
    exp = build(cfg)
    env, model, trainer, robots = exp.env, exp.model, exp.trainer, exp.robot_set
    build_s = time.perf_counter() - t0
    pc = trainer.cfg
    t0 = time.perf_counter()
    ts = jax.block_until_ready(trainer.init(jax.random.PRNGKey(cfg.seed)))
    init_s = time.perf_counter() - t0

    def one_iteration(ts):
        t0 = time.perf_counter()
        ts, batch, _ = trainer.rollout(ts)
        jax.block_until_ready(batch)
        t1 = time.perf_counter()
        ts, m = trainer.update(ts, batch)
        jax.block_until_ready(ts.params)
        return ts, m, t1 - t0, time.perf_counter() - t1

    note(f"{model.arch} on {cfg.env.task}: built in {build_s:.0f} s, initial state {init_s:.0f} s; compiling the "
         f"rollout and the update (the first iteration)...")
    ts, _, compile_rollout, compile_update = one_iteration(ts)  # the first call compiles both phases
    note(f"compiled ({compile_rollout:.0f} s + {compile_update:.0f} s); timing {cfg.bench_iters} iterations...")
    roll, upd, epochs = [], [], []
    for _ in range(cfg.bench_iters):
        ts, m, r, u = one_iteration(ts)
        roll.append(r)
        upd.append(u)
        epochs.append(float(m["epochs_run"]))
    out = {"arch": model.arch, "env": cfg.env.task, "robots": robots, "num_robots": env.num_robots,
           "device": jax.devices()[0].device_kind, "num_envs": pc.num_envs, "rollout_len": pc.rollout_len,
           "steps_per_iter": pc.steps_per_iter, "params": model.num_params(),
           "rollout_sps": pc.steps_per_iter / np.median(roll), "update_sps": pc.steps_per_iter / np.median(upd),
           "end_to_end_sps": pc.steps_per_iter / (np.median(roll) + np.median(upd)),
           "epochs_run_mean": float(np.mean(epochs)), "update_s_per_epoch": float(np.median(upd)) / max(np.mean(epochs), 1e-9),
           "compile_s": {"build": build_s, "init": init_s, "rollout": compile_rollout, "update": compile_update}}
    if cfg.fused:
        note("compiling and timing the fused iteration...")
        t0 = time.perf_counter()
        ts, _ = trainer.iteration(ts)
        jax.block_until_ready(ts.params)
        out["compile_s"]["fused"] = time.perf_counter() - t0
        times = []
        for _ in range(cfg.bench_iters):
            t0 = time.perf_counter()
            ts, m = trainer.iteration(ts)
            jax.block_until_ready(ts.params)
            times.append(time.perf_counter() - t0)
        out["fused_sps"] = pc.steps_per_iter / np.median(times)
    out["hours_per_100M"] = 1e8 / out["end_to_end_sps"] / 3600
    out["peak_memory_gb"] = _memory_gb()
    print(json.dumps(out), flush=True)


def main(argv=None) -> int:
    return cli.main(bench, "bench_train", BenchTrainConfig, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
