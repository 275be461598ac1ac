"""Throughput of the batched environment.

    python -m experiments.bench_env env=ft robots=unimal100/train num_envs=4096
    python -m experiments.bench_env env=csr num_envs=4096 steps=50
    python -m experiments.bench_env mode=physics                    # the 4 MJX substeps only
    python -m experiments.bench_env 'cases=[{env: ft},{env: csr},{env: ft, self_collision: true}]'
    python -m experiments.bench_env env=csr env.iterations=100 env.ls_iterations=50

Each case builds the env, compiles one `lax.scan` of `steps` control steps over `num_envs` envs (random N(0, 0.9)
actions, balanced sampler, automatic resets), runs it `repeats` times and prints one JSON line: control steps per
second (num_envs * steps / median wall time), compile time, the compiled program's memory (arguments, outputs and
temporaries) and the device's peak memory so far. A case is a dict of overrides: `env` (a task name), any key of
the env's options (`self_collision`, `iterations`, `ls_iterations`, ...: mjx_morph.sim.env.EnvConfig), or any other
key of `BenchEnvConfig` below.
"""
from __future__ import annotations

import dataclasses
import json
import statistics
import sys
import time
from typing import Any, Dict, List, Optional

import jax
import jax.numpy as jnp
from mjx_morph.run import register
from mjx_morph.sim import sampling
from mjx_morph.sim.env import EnvConfig, make_env
from mjx_morph.unimal.sets import default_train_set, load_set
from mujoco import mjx  # noqa: I001 - after mjx_morph, whose import silences MJX's missing-Warp message

from . import cli


@dataclasses.dataclass
class BenchEnvConfig:
    env: EnvConfig = dataclasses.field(default_factory=EnvConfig)   # task and simulator options (env=<task>)
    robots: Optional[str] = None        # robot set or path; None: unimal100/train when present, else gen/train
    robots_root: Optional[str] = None
    num_robots: Optional[int] = None    # only the first N robots of the set
    num_envs: int = 4096
    steps: int = 100                    # control steps per timed rollout (one jitted lax.scan)
    repeats: int = 3                    # timed rollouts; the median is reported
    seed: int = 0
    mode: str = "env"                   # env: the full env step; physics: only the MJX substeps of the stacked model
    cases: Optional[List[Dict[str, Any]]] = None   # override dicts, run one after the other (one JSON line each)


register("bench_env_schema", BenchEnvConfig)


def _robots(robots: str | None, robots_root: str | None, num_robots: int | None):
    name = robots or default_train_set(robots_root)
    rs = list(load_set(name, robots_root).robots)
    if num_robots:
        rs = rs[:int(num_robots)]
    return name, rs


def run_case(c: dict) -> dict:
    """One case: `c` holds the keys of BenchEnvConfig with `env` an EnvConfig."""
    name, rs = _robots(c.get("robots"), c.get("robots_root"), c.get("num_robots"))
    config = c["env"]
    print(f"[bench_env] {config.task}: building the env of {len(rs)} robots, then compiling and timing...",
          file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    env = make_env(rs, config=config)
    build_s = time.perf_counter() - t0
    pairs = env.sm.self_contact
    print(f"[bench_env] {pairs.line()}", file=sys.stderr, flush=True)
    n, steps = int(c["num_envs"]), int(c["steps"])
    sampler = sampling.init(env.num_robots, "balanced")
    key = jax.random.PRNGKey(int(c["seed"]))
    state = jax.jit(env.init, static_argnums=1)(key, n, sampler)
    jax.block_until_ready(state)

    if c["mode"] == "physics":
        sm = env.sm

        def one(robot, qpos, qvel, warm, ctrl):
            m = sm.model_for(robot)
            d = env._template.replace(qpos=qpos, qvel=qvel, qacc_warmstart=warm, ctrl=ctrl)
            with env.physics():     # the env's precision and contact rules (they size the contact arrays)
                d = jax.lax.fori_loop(0, config.substeps, lambda i, dd: mjx.step(m, dd), d)
            return d.qpos, d.qvel, d.qacc_warmstart

        def rollout(carry, key):
            def body(carry, k):
                qpos, qvel, warm = carry
                ctrl = jnp.clip(0.9 * jax.random.normal(k, (n, sm.mj_models[0].nu)), -1, 1)
                qpos, qvel, warm = jax.vmap(one)(state.episode.robot, qpos, qvel, warm, ctrl)
                return (qpos, qvel, warm), qpos[:, 2].mean()
            return jax.lax.scan(body, carry, jax.random.split(key, steps))

        carry = (state.physics.qpos, state.physics.qvel, state.physics.qacc_warmstart)
    else:
        def rollout(carry, key):
            def body(st, k):
                a = 0.9 * jax.random.normal(k, (n, 24))
                st = env.vstep(st, a, sampler)
                return st, (st.reward.sum(), st.done.sum(), (st.done & st.ended.unstable).sum())
            return jax.lax.scan(body, carry, jax.random.split(key, steps))

        carry = state

    f = jax.jit(rollout, donate_argnums=0)
    t0 = time.perf_counter()
    compiled = f.lower(carry, key).compile()
    compile_s = time.perf_counter() - t0
    mem = compiled.memory_analysis()
    carry, out = compiled(carry, jax.random.fold_in(key, 0))      # warm-up
    jax.block_until_ready(out)
    times = []
    dones = unstable = 0
    for r in range(int(c["repeats"])):
        t0 = time.perf_counter()
        carry, out = compiled(carry, jax.random.fold_in(key, r + 1))
        jax.block_until_ready(out)
        times.append(time.perf_counter() - t0)
        if c["mode"] != "physics":
            dones += int(out[1].sum())
            unstable += int(out[2].sum())
    dt = statistics.median(times)
    dev = jax.devices()[0]
    stats = dev.memory_stats() or {}
    res = {
        "env": config.task, "mode": c["mode"], "robots": name, "num_robots": env.num_robots,
        "tree_bodies": env.sm.tree.num_slots, "nv": int(env.sm.mj_models[0].nv), "num_envs": n, "steps": steps,
        "solver_iterations": config.iterations, "ls_iterations": config.ls_iterations,
        "self_collision": config.self_collision,
        "self_pairs": pairs.kept, "self_pair_candidates": pairs.candidates, "contacts": pairs.mjx_contacts,
        "control_steps_per_s": round(n * steps / dt, 1), "rollout_s": round(dt, 4),
        "compile_s": round(compile_s, 1), "build_s": round(build_s, 1),
        "program_mem_gb": round((getattr(mem, "argument_size_in_bytes", 0) + getattr(mem, "output_size_in_bytes", 0)
                                 + getattr(mem, "temp_size_in_bytes", 0)) / 2**30, 3) if mem is not None else None,
        "peak_mem_gb": round(stats.get("peak_bytes_in_use", 0) / 2**30, 3) if stats else None,
        "episodes_ended": dones, "unstable": unstable,
        "device": dev.device_kind, "jax": jax.__version__,
    }
    if env.task.uses_hfield:
        res["hfield_patch"] = env.terrain.patch_size
    return res


def case_config(base: BenchEnvConfig, case: dict) -> dict:
    """The settings of one case: `base` with the case's overrides (`env` names the task; EnvConfig keys go to the
    env's options)."""
    case = dict(case)
    env_fields = {f.name for f in dataclasses.fields(EnvConfig)}
    env_over = {k: case.pop(k) for k in list(case) if k in env_fields}
    if "env" in case:
        env_over["task"] = case.pop("env")
    known = {f.name for f in dataclasses.fields(BenchEnvConfig)} - {"cases", "env"}
    unknown = sorted(set(case) - known)
    if unknown:
        raise ValueError(f"cases: unknown key(s) {unknown}; expected env, EnvConfig keys or {sorted(known)}")
    c = {f.name: getattr(base, f.name) for f in dataclasses.fields(BenchEnvConfig) if f.name != "cases"}
    c.update(case)
    c["env"] = dataclasses.replace(base.env, **env_over)
    return c


def bench(cfg: BenchEnvConfig) -> None:
    for case in cfg.cases or [{}]:
        print(json.dumps(run_case(case_config(cfg, case))), flush=True)


def main(argv=None) -> int:
    return cli.main(bench, "bench_env", BenchEnvConfig, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
