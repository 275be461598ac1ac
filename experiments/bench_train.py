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
makes comparing learner variants quick. `mode=rollout` times the rollout alone (physics and acting), for comparing
physics variants (`env.self_collision=false`, `env.iterations=...`, `env.linalg=pallas`) as the training loop runs
them.

`profile=true` writes a trace of one call of each timed phase (TensorBoard's profile plugin or Perfetto read it:
`profile_dir/<phase>/plugins/profile/<run>/*.xplane.pb`, with the compiled program beside it as `<phase>_hlo.txt`)
and prints, on stderr, the phase's top device kernels by time with the code each came from (the innermost Python
frame XLA recorded for it: file, function, line) and the kernel time per stage: the innermost function outside
MJX's math helpers and the libraries (`mjx/smooth.py:kinematics`, `mjx/solver.py:solve`,
`mjx/collision_driver.py:collision`, `mjx_morph/nets/layers.py:EncoderLayer.__call__`, ...), which says which step of
the physics or which layer of the networks the time goes to.

    python -m experiments.bench_train env=ft robots=unimal100/train arch=rmomo mode=rollout profile=true
"""
from __future__ import annotations

import dataclasses
import glob
import json
import math
import os
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
from mjx_morph.sim import linalg

from . import cli, flops


@dataclasses.dataclass
class BenchTrainConfig(RunConfig):
    bench_iters: int = 4                    # timed iterations per phase, after one warm-up iteration (compilation)
    fused: bool = True                      # also time the fused one-jit iteration (mode=both)
    mode: str = "both"                      # both: rollout and update; update: the update alone, synthetic batch;
    #                                         rollout: the rollout alone
    profile: bool = False                   # write a device trace of one call of each phase and print its top ops
    profile_dir: str = "bench_trace"        # where the trace goes
    top_ops: int = 15                       # how many kernels the profile summary lists (and source files)
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
    # (B, N, ...) -> (1, ...): one env's observation, for the parameter init
    one_env = jax.tree.map(lambda s: jnp.zeros((1, *s.shape[2:]), s.dtype), abstract.tail_obs)
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


def top_ops(trace_dir: str, n: int | None = None) -> tuple[list[dict], list[str]]:
    """The GPU kernels of a trace by total time (name, milliseconds, share of kernel time, calls; the first n, or
    all), and the names of the device planes and lines (what the trace holds)."""
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


def _hlo_table(hlo_text: str, name: str) -> dict[int, tuple]:
    """One of the tables at the end of an HLO module's text (FileNames, FunctionNames, FileLocations, StackFrames):
    id -> its fields (a string, or the numbers of a {key=value ...} record in order)."""
    m = re.search(rf"^{name}\n(.*?)(?=^[A-Za-z]\w*\n|\Z)", hlo_text, flags=re.M | re.S)
    out = {}
    for line in (m.group(1).splitlines() if m else []):
        if q := re.match(r'^(\d+) "(.*)"$', line):
            out[int(q.group(1))] = q.group(2)
        elif q := re.match(r"^(\d+) \{(.*)\}$", line):
            out[int(q.group(1))] = tuple(int(v) for v in re.findall(r"=(\d+)", q.group(2)))
    return out


def short_path(path: str) -> str:
    """A source file as the profile groups it: `mjx/solver.py`, `mjx_morph/nets/layers.py`, `flax/linen/...`."""
    for marker, prefix in (("/mujoco/mjx/_src/", "mjx/"), ("/site-packages/", ""), ("/mjx_morph/", "mjx_morph/"),
                           ("/experiments/", "experiments/"), ("/tests/", "tests/")):
        if marker in path:
            return prefix + path.rsplit(marker, 1)[1]
    return path.rsplit("/", 1)[-1]


#: source files whose functions serve every stage (MJX's math, tree scans and Jacobians; JAX and Flax internals): a
#: kernel is attributed to the innermost frame outside them
HELPER_FILES = ("mjx/math.py", "mjx/scan.py", "mjx/support.py")


def _is_helper(file: str) -> bool:
    return file in HELPER_FILES or not file.startswith(("mjx/", "mjx_morph/", "experiments/", "tests/"))


def hlo_sources(hlo_text: str) -> dict[str, dict]:
    """Kernel name (an HLO instruction's name with '.' and '-' as '_') -> its result shape ("shape"), the JAX op it
    came from ("jax_op"), and, when the module carries its stack-frame tables, the Python frames XLA recorded for
    it ("stack": file:function:line from the innermost outwards, at most 16; "where": the innermost) and the stage
    it belongs to ("stage": file:function of the innermost frame outside HELPER_FILES and the libraries, e.g.
    `mjx/smooth.py:kinematics`)."""
    files, funcs = _hlo_table(hlo_text, "FileNames"), _hlo_table(hlo_text, "FunctionNames")
    locations, frames = _hlo_table(hlo_text, "FileLocations"), _hlo_table(hlo_text, "StackFrames")

    def chain(frame: int, depth: int = 16) -> list[tuple[str, str, int]]:
        """(file, function, line) from the innermost frame outwards. XLA prints a frame's parent as its id + 1
        (0: none)."""
        out, seen = [], set()
        while frame in frames and frame not in seen and len(out) < depth:
            seen.add(frame)
            location_id, parent = frames[frame][:2]
            loc = locations.get(location_id)
            if loc:
                out.append((short_path(files.get(loc[0], "?")), funcs.get(loc[1], "?"), loc[2]))
            frame = parent - 1
        return out

    out = {}
    for m in re.finditer(r"^\s*(?:ROOT )?%?([\w.\-]+) = (\S+) [^\n]*?metadata=\{([^}]*)\}", hlo_text, flags=re.M):
        name = m.group(1).replace(".", "_").replace("-", "_")
        if name in out:
            continue
        op = re.search(r'op_name="([^"]*)"', m.group(3))
        rec = {"shape": m.group(2)[:60], "jax_op": op.group(1)[-140:] if op else "", "where": "", "stage": ""}
        frame = re.search(r"stack_frame_id=(\d+)", m.group(3))
        frames_out = chain(int(frame.group(1))) if frame else []
        if frames_out:
            rec["stack"] = [":".join(map(str, f)) for f in frames_out]
            rec["where"] = rec["stack"][0]
            file, func, _ = next((f for f in frames_out if not _is_helper(f[0])), frames_out[0])
            rec["stage"] = f"{file}:{func.split('.<locals>')[0]}"
        out[name] = rec
    return out


def time_by_stage(ops: list[dict], sources: dict[str, dict]) -> list[dict]:
    """Kernel time summed per stage (`hlo_sources`; kernels without a recorded frame: "(none)"), largest first."""
    per = defaultdict(lambda: {"ms": 0.0, "share": 0.0, "kernels": 0})
    for o in ops:
        rec = per[sources.get(o["op"], {}).get("stage") or "(none)"]
        rec["ms"] += o["ms"]
        rec["share"] += o["share"]
        rec["kernels"] += 1
    return [{"stage": k, **v} for k, v in sorted(per.items(), key=lambda kv: -kv[1]["ms"])]


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


def _profile(cfg: BenchTrainConfig, phase: str, fn, args: tuple, out: dict) -> None:
    """Trace one call of the jitted `fn(*args)` into profile_dir/<phase>; its top kernels and the kernel time per
    stage (`time_by_stage`) go to out["profile"][phase] and to stderr."""
    trace_dir = Path(cfg.profile_dir) / phase
    note(f"profiling one {phase} into {trace_dir} ...")
    with jax.profiler.trace(str(trace_dir)):
        jax.block_until_ready(fn(*args))
    ops, planes = top_ops(str(trace_dir))
    hlo = fn.lower(*args).compile().as_text()
    (Path(cfg.profile_dir) / f"{phase}_hlo.txt").write_text(hlo)
    sources = hlo_sources(hlo)
    top = [{**o, **sources.get(o["op"], {})} for o in ops[:cfg.top_ops]]
    stages = time_by_stage(ops, sources)[:cfg.top_ops]
    out.setdefault("profile", {})[phase] = {"dir": str(trace_dir), "top_ops": top, "by_stage": stages,
                                            "trace_planes": planes}
    if not ops:
        note("no device kernels in the trace (a CPU run?): open it in TensorBoard or Perfetto")
        return
    for o in top:
        note(f"{phase} {o['share']:6.1%} {o['ms']:9.2f} ms {o['calls']:7d}x  {o['op'][:36]:36s} "
             f"{o.get('where') or o.get('jax_op', '')}")
    for st in stages:
        note(f"{phase} {st['share']:6.1%} {st['ms']:9.2f} ms {st['kernels']:5d} kernels  {st['stage']}")


def _timed(call, n: int) -> tuple[float, object]:
    """The median wall time of n calls of `call()` (each waited for until its outputs are ready) and the last
    outputs."""
    times, res = [], None
    for _ in range(n):
        t0 = time.perf_counter()
        res = jax.block_until_ready(call())
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), res


def _update_alone(cfg: BenchTrainConfig, trainer: Trainer, steps: int, build_s: float, out: dict):
    """mode=update: the update on a synthetic batch, every epoch run."""
    t0 = time.perf_counter()
    ts, batch = synthetic_state_and_batch(trainer, jax.random.PRNGKey(cfg.seed))
    if trainer.num_seeds is not None:
        ts, batch = stack_seeds([ts] * trainer.num_seeds), stack_seeds([batch] * trainer.num_seeds)
    jax.block_until_ready(batch)
    init_s = time.perf_counter() - t0
    note(f"{trainer.model.arch}: built in {build_s:.0f} s, synthetic batch {init_s:.0f} s; compiling the update...")
    compile_update, _ = _timed(lambda: trainer.update(ts, batch), 1)
    note(f"compiled ({compile_update:.0f} s); timing {cfg.bench_iters} updates...")
    med, (_, m) = _timed(lambda: trainer.update(ts, batch), cfg.bench_iters)
    out.update(update_sps=steps / med, update_s=med, epochs_run_mean=float(np.mean(m["epochs_run"])),
               compile_s={"build": build_s, "batch": init_s, "update": compile_update})
    return ts, batch


def _iterations(cfg: BenchTrainConfig, trainer: Trainer, steps: int, build_s: float, out: dict):
    """mode=both / rollout: real iterations from the initial state, each phase timed as its own jitted call; then
    (mode=both, fused=true) the fused one-jit iteration."""
    t0 = time.perf_counter()
    ts = jax.block_until_ready(trainer.init(seed_keys(cfg.seeds) if cfg.seeds else jax.random.PRNGKey(cfg.seed)))
    init_s = time.perf_counter() - t0
    update = cfg.mode == "both"

    def one_iteration(ts):
        t0 = time.perf_counter()
        ts, batch, _ = jax.block_until_ready(trainer.rollout(ts))
        t1 = time.perf_counter()
        ts, m = jax.block_until_ready(trainer.update(ts, batch)) if update else (ts, None)
        return ts, batch, m, t1 - t0, time.perf_counter() - t1

    note(f"{trainer.model.arch} on {cfg.env.task}: built in {build_s:.0f} s, initial state {init_s:.0f} s; compiling "
         f"the rollout{' and the update' if update else ''} (the first iteration)...")
    ts, batch, _, compile_rollout, compile_update = one_iteration(ts)
    note(f"compiled ({compile_rollout:.0f} s + {compile_update:.0f} s); timing {cfg.bench_iters} iterations...")
    roll, upd, epochs = [], [], []
    for _ in range(cfg.bench_iters):
        ts, batch, m, r, u = one_iteration(ts)
        roll.append(r)
        upd.append(u)
        if update:
            epochs.append(float(np.mean(m["epochs_run"])))
    out.update(rollout_sps=steps / np.median(roll),
               compile_s={"build": build_s, "init": init_s, "rollout": compile_rollout})
    if not update:
        return ts, batch
    med = float(np.median(upd))
    out.update(update_sps=steps / med, update_s=med, end_to_end_sps=steps / (np.median(roll) + med),
               epochs_run_mean=float(np.mean(epochs)), update_s_per_epoch=med / max(np.mean(epochs), 1e-9),
               hours_per_100M=(np.median(roll) + med) * 1e8 / steps / 3600)
    out["compile_s"]["update"] = compile_update
    if cfg.fused:
        note("compiling and timing the fused iteration...")
        out["compile_s"]["fused"], (ts, _) = _timed(lambda: trainer.iteration(ts), 1)
        fused, (ts, _) = _timed(lambda: trainer.iteration(ts), cfg.bench_iters)
        out["fused_sps"] = steps / fused
    if trainer.num_seeds is not None:
        out["per_run_end_to_end_sps"] = out["end_to_end_sps"] / trainer.num_seeds
        out["hours_per_100M_each_run"] = out["hours_per_100M"] * trainer.num_seeds
    return ts, batch


def bench(cfg: BenchTrainConfig) -> None:
    if cfg.mode not in ("both", "update", "rollout"):
        raise ValueError(f"mode={cfg.mode!r}: expected both, update or rollout")
    if cfg.mode == "update":
        cfg = dataclasses.replace(cfg, ppo=dataclasses.replace(cfg.ppo, kl_threshold=math.inf))
    t0 = time.perf_counter()
    exp = build(cfg)
    env, model, trainer, robots = exp.env, exp.model, exp.trainer, exp.robot_set
    build_s = time.perf_counter() - t0
    pc = trainer.cfg
    steps = pc.steps_per_iter * (trainer.num_seeds or 1)      # env steps of one iteration, all seeds together
    out = {"arch": model.arch, "seeds": trainer.num_seeds or 1, "env": cfg.env.task, "robots": robots,
           "num_robots": env.num_robots, "device": jax.devices()[0].device_kind, "precision": cfg.precision,
           "mode": cfg.mode, "self_collision": cfg.env.self_collision, "linalg": linalg.resolve(cfg.env.linalg),
           "num_envs": pc.num_envs, "rollout_len": pc.rollout_len, "minibatch_size": pc.minibatch_size,
           "steps_per_iter": pc.steps_per_iter, "params": model.num_params(),
           "xla_flags": os.environ.get("XLA_FLAGS", "")}
    phases = _update_alone if cfg.mode == "update" else _iterations
    ts, batch = phases(cfg, trainer, steps, build_s, out)
    if cfg.mode != "rollout":   # the FLOPs of the worst case (every epoch), scaled by the epochs the KL stop let run
        _flops_out(out, trainer, ts, batch, out["update_s"] / max(out["epochs_run_mean"] / pc.epochs, 1e-9),
                   cfg.precision)
    out["peak_memory_gb"] = _memory_gb()
    if cfg.profile:
        if cfg.mode != "update":
            _profile(cfg, "rollout", trainer.rollout, (ts,), out)
        if cfg.mode != "rollout":
            _profile(cfg, "update", trainer.update, (ts, batch), out)
    print(json.dumps(out), flush=True)


def main(argv=None) -> int:
    return cli.main(bench, "bench_train", BenchTrainConfig, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
