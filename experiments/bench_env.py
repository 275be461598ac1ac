"""Throughput of the batched environment.

    python -m experiments.bench_env env=ft robots=unimal100/train num_envs=4096
    python -m experiments.bench_env env=csr num_envs=4096 steps=50
    python -m experiments.bench_env mode=physics                    # the 4 MJX substeps only
    python -m experiments.bench_env 'cases=[{env: ft},{env: csr},{env: ft, self_collision: true}]'

Each case builds the env, compiles one `lax.scan` of `steps` control steps over `num_envs` envs (random N(0, 0.9)
actions, balanced sampler, automatic resets), runs it `repeats` times and prints one JSON line: control steps per
second (num_envs * steps / median wall time), compile time, the compiled program's memory (arguments, outputs and
temporaries) and the device's peak memory so far. Case keys: env (task name), self_collision, solver_iterations,
ls_iterations, num_envs, steps, num_robots, group, mode, unroll_substeps, robots.
"""
from __future__ import annotations

import json
import statistics
import time

import hydra
import jax
import jax.numpy as jnp
from omegaconf import DictConfig, OmegaConf


def _robots(robots: str | None, robots_root: str | None, num_robots: int | None, group: str | None):
    from mjx_morph.sim.supertree import group_robots
    from mjx_morph.unimal.sets import default_train_set, load_set
    name = robots or default_train_set(robots_root)
    rs = list(load_set(name, robots_root).robots)
    if num_robots:
        rs = rs[:int(num_robots)]
    if group:
        k, n = (int(x) for x in str(group).split("/"))
        rs = [rs[i] for i in group_robots(rs, n)[k]]
    return name, rs


def run_case(c: dict) -> dict:
    from mujoco import mjx

    from mjx_morph.sim import sampling
    from mjx_morph.sim.env import EnvConfig, make_env

    name, rs = _robots(c.get("robots"), c.get("robots_root"), c.get("num_robots"), c.get("group"))
    config = EnvConfig(task=c["env"], iterations=int(c["solver_iterations"]), ls_iterations=int(c["ls_iterations"]),
                       self_collision=bool(c["self_collision"]), episode_length=int(c["episode_length"]),
                       unroll_substeps=bool(c["unroll_substeps"]))
    t0 = time.perf_counter()
    env = make_env(rs, config=config)
    build_s = time.perf_counter() - t0
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
        "env": c["env"], "mode": c["mode"], "robots": name, "num_robots": env.num_robots,
        "tree_bodies": env.sm.tree.num_slots, "nv": int(env.sm.mj_models[0].nv), "num_envs": n, "steps": steps,
        "solver_iterations": config.iterations, "ls_iterations": config.ls_iterations,
        "self_collision": config.self_collision, "group": c.get("group"),
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


@hydra.main(version_base=None, config_path="conf", config_name="bench_env")
def main(cfg: DictConfig) -> None:
    base = OmegaConf.to_container(cfg, resolve=True)
    envcfg = base.pop("env")
    cases = base.pop("cases") or [{}]
    for case in cases:
        c = dict(base)
        c.update({"env": envcfg["name"], "solver_iterations": envcfg.get("solver_iterations", 5),
                  "ls_iterations": envcfg.get("ls_iterations", 8),
                  "self_collision": envcfg.get("self_collision", False),
                  "episode_length": envcfg.get("episode_length", 1000)})
        c.update(case)
        print(json.dumps(run_case(c)), flush=True)


if __name__ == "__main__":
    main()
