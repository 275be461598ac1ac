"""Training throughput: `python -m experiments.bench_train env=ft arch=rmomo` prints one JSON line.

Per phase (rollout: physics + acting; update: GAE, all PPO epochs and minibatches that the KL stop lets run): env
steps per second, compile time; for the update also its matmul FLOPs per iteration (counted on the jaxpr, every
minibatch of every epoch: `experiments/flops.py`), the achieved TFLOP/s and the model FLOP utilisation (MFU) against
the device's dense peak at the run's `precision` (fp32 | tf32 | bf16); peak device memory; the mean number of epochs
run. After one warm-up iteration (compilation), `bench_iters` iterations are timed with the two phases as separate
jitted calls, then (fused=true) the same number as the single fused jitted iteration.

    python -m experiments.bench_train env=ft arch=rmomo precision=bf16
    python -m experiments.bench_train arch=rmomo mode=update            # the update alone, on a synthetic batch
    python -m experiments.bench_train arch=rmomo mode=update profile=true profile_dir=/tmp/trace

`seeds=[0,1,...]` times S runs side by side in one program (`Trainer(seeds=S)`): the rates are then env steps/s of
all seeds together, and `per_run_*` the rates each run sees.

`mode=update` skips the physics: it times the update on a batch of random observations of the right shapes with
the KL stop off (`ppo.kl_threshold` = inf, so every epoch runs: the worst case), and compiles nothing else, which
makes comparing learner variants quick. `profile=true` writes a trace of one timed update (TensorBoard's profile
plugin or Perfetto read it: `profile_dir/plugins/profile/<run>/*.xplane.pb`) and prints the update's top device
ops by time on stderr (their share and the JAX source of each).
"""
from __future__ import annotations

import dataclasses
import glob
import json
import math
import re
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np

from mjx_morph.ppo.trainer import Batch, Trainer, seed_keys, seed_state, stack_seeds
from mjx_morph.run import RunConfig, build, register

from . import cli, flops


@dataclasses.dataclass
class BenchTrainConfig(RunConfig):
    bench_iters: int = 4                    # timed iterations per phase, after one warm-up iteration (compilation)
    fused: bool = True                      # also time the fused one-jit iteration (mode=both)
    mode: str = "both"                      # both: rollout and update; update: the update alone, synthetic batch
    profile: bool = False                   # write a device trace of one update and print its top ops
    profile_dir: str = "bench_trace"        # where the trace goes
    top_ops: int = 15                       # how many ops the profile summary lists
    compile_cache: Optional[str] = None     # benchmarks measure compilation: never from the cache


register("bench_train_schema", BenchTrainConfig)


def _memory_gb() -> float:
    stats = jax.devices()[0].memory_stats() or {}
    return stats.get("peak_bytes_in_use", float("nan")) / 1e9


def note(text: str) -> None:
    """Progress on stderr, so that stdout stays one JSON line per case."""
    print(f"[bench_train] {text}", file=sys.stderr, flush=True)


def synthetic_state_and_batch(trainer: Trainer, key: jax.Array):
    """A train state with freshly initialised parameters and optimiser, and a batch of the rollout's shapes filled
    with random observations, actions and targets (episode starts at rate 1/200), without running the physics: only
    the initial state's shapes are traced (`Trainer.abstract_state`)."""
    env, model, cfg = trainer.env, trainer.model, trainer.cfg
    abstract = trainer.abstract_state()
    zeros = lambda s: jnp.zeros(s.shape, s.dtype)
    ts = jax.tree.map(zeros, abstract)
    k_model, k_obs, k_act, k_first, k_robot, ka, kb, kc, kd = jax.random.split(key, 9)
    one_env = jax.tree.map(lambda s: jnp.zeros((1, *s.shape[2:]), s.dtype), abstract.tail_obs)   # (B, N, ...) -> (1, ...)
    params = model.init(k_model, env.robots, one_env)
    ts = ts.replace(params=params, opt_state=trainer.tx.init(params), key=key)
    t, n, k = cfg.rollout_len, cfg.num_envs, trainer.num_windows
    t_all = cfg.burn_in + t
    normal = lambda key, shape: jax.random.normal(key, shape, jnp.float32)
    tail = abstract.tail_obs
    obs = tail._replace(
        proprio=normal(k_obs, (t_all, *tail.proprio.shape[1:])),
        prev_action=jnp.clip(normal(k_act, (t_all, *tail.prev_action.shape[1:])), -1, 1),
        robot=jnp.broadcast_to(jax.random.randint(k_robot, (n,), 0, env.num_robots), (t_all, n)),
        hfield=None if tail.hfield is None else normal(k_obs, (t_all, *tail.hfield.shape[1:])))
    starts = jax.tree.map(lambda s: jnp.zeros((k, *s.shape), s.dtype), abstract.carry)
    batch = Batch(obs=obs, first=jax.random.uniform(k_first, (t_all, n)) < 1 / 200, starts=starts,
                  action=normal(ka, (t, n, tail.prev_action.shape[-1])), logp=normal(kb, (t, n)) - 20.0,
                  value=normal(kc, (t, n)), adv=normal(kd, (t, n)), ret=normal(kd, (t, n)))
    return ts, batch


def top_ops(trace_dir: str, n: int) -> tuple[list[dict], list[str]]:
    """The GPU kernels of a trace by total time (name, milliseconds, share of kernel time, calls), and the names of
    the device planes and lines (what the trace holds)."""
    from jax.profiler import ProfileData
    files = sorted(glob.glob(f"{trace_dir}/**/*.xplane.pb", recursive=True))
    if not files:
        return [], []
    data = ProfileData.from_file(files[-1])
    total, per, seen = 0.0, defaultdict(lambda: {"ns": 0.0, "calls": 0}), []
    for plane in data.planes:
        if not plane.name.startswith("/device:"):
            continue
        lines = list(plane.lines)
        seen.append(f"{plane.name}: " + ", ".join(sorted({line.name for line in lines})))
        ops = [line for line in lines if line.name == "XLA Ops"] or [line for line in lines if "Stream" in line.name]
        for line in ops:
            for ev in line.events:
                rec = per[ev.name]
                rec["ns"] += ev.duration_ns
                rec["calls"] += 1
                total += ev.duration_ns
    rows = sorted(per.items(), key=lambda kv: -kv[1]["ns"])[:n]
    return [{"op": k, "ms": v["ns"] / 1e6, "share": v["ns"] / max(total, 1.0), "calls": v["calls"]}
            for k, v in rows], seen


def hlo_sources(hlo_text: str) -> dict[str, str]:
    """Kernel name (an HLO instruction's name with '.' as '_') -> its shape and the JAX op it came from."""
    out = {}
    for m in re.finditer(r"^\s*(?:ROOT )?%?([\w.\-]+) = (\S+) [^\n]*?metadata=\{op_name=\"([^\"]*)\"", hlo_text,
                         flags=re.M):
        out.setdefault(m.group(1).replace(".", "_").replace("-", "_"), f"{m.group(2)[:60]} {m.group(3)[-140:]}")
    return out


def _flops_out(out: dict, trainer: Trainer, ts, batch, update_s: float, precision: str) -> None:
    trips = trainer.cfg.epochs * trainer.num_minibatches       # the minibatch loop, every epoch run
    if trainer.num_seeds is not None:      # one seed's program, counted once per seed
        f = trainer.num_seeds * flops.count(trainer._update, seed_state(ts, 0), seed_state(batch, 0),
                                            while_trips=trips)
    else:
        f = flops.count(trainer._update, ts, batch, while_trips=trips)
    out["update_matmul_gflop_per_iter"] = f / 1e9
    out["update_matmul_gflop_per_env_step"] = f / (trainer.cfg.steps_per_iter * (trainer.num_seeds or 1)) / 1e9
    out["update_tflops"] = f / update_s / 1e12 if update_s > 0 else float("nan")
    peak = flops.peak_flops(jax.devices()[0].device_kind, precision)
    out["update_mfu"] = out["update_tflops"] * 1e12 / peak if peak else None
    out["flops_source"] = "matmul FLOPs counted on the jaxpr (experiments/flops.py), all epochs"


def _profile(cfg: BenchTrainConfig, trainer: Trainer, ts, batch, out: dict) -> None:
    note(f"profiling one update into {cfg.profile_dir} ...")
    with jax.profiler.trace(cfg.profile_dir):
        ts2, _ = trainer.update(ts, batch)
        jax.block_until_ready(ts2.params)
    ops, planes = top_ops(cfg.profile_dir, cfg.top_ops)
    hlo = trainer.update.lower(ts, batch).compile().as_text()
    Path(cfg.profile_dir).mkdir(parents=True, exist_ok=True)
    (Path(cfg.profile_dir) / "update_hlo.txt").write_text(hlo)
    sources = hlo_sources(hlo)
    for o in ops:
        o["source"] = sources.get(o["op"], "")
    out["profile_dir"] = cfg.profile_dir
    out["top_ops"] = ops
    out["trace_planes"] = planes
    if not ops:
        note("no device kernels in the trace (a CPU run?): open it in TensorBoard or Perfetto")
    for o in ops:
        note(f"{o['share']:6.1%} {o['ms']:9.2f} ms {o['calls']:7d}x  {o['op'][:36]:36s} {o['source']}")


def bench(cfg: BenchTrainConfig) -> None:
    if cfg.mode not in ("both", "update"):
        raise ValueError(f"mode={cfg.mode!r}: expected both or update")
    if cfg.mode == "update":
        cfg = dataclasses.replace(cfg, ppo=dataclasses.replace(cfg.ppo, kl_threshold=math.inf))
    t0 = time.perf_counter()
    exp = build(cfg)
    env, model, trainer, robots = exp.env, exp.model, exp.trainer, exp.robot_set
    build_s = time.perf_counter() - t0
    pc = trainer.cfg
    runs = len(cfg.seeds) if cfg.seeds else 1
    steps = pc.steps_per_iter * runs          # env steps of one iteration, all seeds together
    out = {"arch": model.arch, "seeds": runs, "env": cfg.env.task, "robots": robots, "num_robots": env.num_robots,
           "device": jax.devices()[0].device_kind, "precision": cfg.precision, "mode": cfg.mode,
           "self_collision": cfg.env.self_collision, "num_envs": pc.num_envs, "rollout_len": pc.rollout_len,
           "minibatch_size": pc.minibatch_size, "steps_per_iter": pc.steps_per_iter, "params": model.num_params()}

    if cfg.mode == "update":
        t0 = time.perf_counter()
        ts, batch = synthetic_state_and_batch(trainer, jax.random.PRNGKey(cfg.seed))
        if trainer.num_seeds is not None:
            ts, batch = stack_seeds([ts] * runs), stack_seeds([batch] * runs)
        jax.block_until_ready(batch)
        init_s = time.perf_counter() - t0
        note(f"{model.arch}: built in {build_s:.0f} s, synthetic batch {init_s:.0f} s; compiling the update...")
        t0 = time.perf_counter()
        ts1, m = trainer.update(ts, batch)
        jax.block_until_ready(ts1.params)
        compile_update = time.perf_counter() - t0
        note(f"compiled ({compile_update:.0f} s); timing {cfg.bench_iters} updates...")
        upd = []
        for _ in range(cfg.bench_iters):
            t0 = time.perf_counter()
            ts1, m = trainer.update(ts, batch)
            jax.block_until_ready(ts1.params)
            upd.append(time.perf_counter() - t0)
        med = float(np.median(upd))
        out.update(update_sps=steps / med, update_s=med, epochs_run_mean=float(np.mean(m["epochs_run"])),
                   compile_s={"build": build_s, "batch": init_s, "update": compile_update})
    else:
        t0 = time.perf_counter()
        ts = jax.block_until_ready(trainer.init(seed_keys(cfg.seeds) if cfg.seeds else jax.random.PRNGKey(cfg.seed)))
        init_s = time.perf_counter() - t0

        def one_iteration(ts):
            t0 = time.perf_counter()
            ts, batch, _ = trainer.rollout(ts)
            jax.block_until_ready(batch)
            t1 = time.perf_counter()
            ts, m = trainer.update(ts, batch)
            jax.block_until_ready(ts.params)
            return ts, batch, m, t1 - t0, time.perf_counter() - t1

        note(f"{model.arch} on {cfg.env.task}: built in {build_s:.0f} s, initial state {init_s:.0f} s; compiling "
             f"the rollout and the update (the first iteration)...")
        ts, batch, _, compile_rollout, compile_update = one_iteration(ts)  # the first call compiles both phases
        note(f"compiled ({compile_rollout:.0f} s + {compile_update:.0f} s); timing {cfg.bench_iters} iterations...")
        roll, upd, epochs = [], [], []
        for _ in range(cfg.bench_iters):
            ts, batch, m, r, u = one_iteration(ts)
            roll.append(r)
            upd.append(u)
            epochs.append(float(np.mean(m["epochs_run"])))
        med = float(np.median(upd))
        out.update(rollout_sps=steps / np.median(roll), update_sps=steps / med, update_s=med,
                   end_to_end_sps=steps / (np.median(roll) + med),
                   epochs_run_mean=float(np.mean(epochs)), update_s_per_epoch=med / max(np.mean(epochs), 1e-9),
                   compile_s={"build": build_s, "init": init_s, "rollout": compile_rollout, "update": compile_update})
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
            out["fused_sps"] = steps / np.median(times)
        out["hours_per_100M"] = 1e8 / out["end_to_end_sps"] / 3600
        if runs > 1:
            out["per_run_end_to_end_sps"] = out["end_to_end_sps"] / runs
            out["hours_per_100M_each_run"] = out["hours_per_100M"] * runs
    # the FLOPs of the worst case (every epoch); scaled by the epochs that ran when the KL stop cut the update
    _flops_out(out, trainer, ts, batch, med / max(out["epochs_run_mean"] / pc.epochs, 1e-9), cfg.precision)
    out["peak_memory_gb"] = _memory_gb()
    if cfg.profile:
        _profile(cfg, trainer, ts, batch, out)
    print(json.dumps(out), flush=True)


def main(argv=None) -> int:
    return cli.main(bench, "bench_train", BenchTrainConfig, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
