"""One of the processes of tests/test_multihost.py: started once per process with the settings in MJX_MORPH_COORDINATOR,
MJX_MORPH_NUM_PROCESSES, MJX_MORPH_PROCESS_ID and 2 virtual CPU devices each (XLA_FLAGS), it trains the tiny ToyEnv
config of tests/multi_device_run.py over every process's devices, twice:

1. the trainer alone, 4 iterations (`Trainer.iteration`);
2. through `train()` (with phase_timing: rollout and update as two jitted calls): 2 iterations (stop_after=2, a
   checkpoint), then a resume to iteration 4;

then process 0 alone reads the last checkpoint back (as evaluation does) while the others wait. It also builds the
MJX env of one shipped robot and lists its arrays that live on another process's device (a jitted function cannot
close over them). Each process writes
its final parameters to <out>/<name>_<process id>.npz and prints one JSON line of what it saw. The model is the
feed-forward MetaMorph: it compiles in half the time of R-MoMo, and its empty burn-in tails test checkpoints with
zero-size arrays (test_devices.py checks the recurrent state's layout over devices)."""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import jax
import numpy as np

from mjx_morph.nets.zoo import ModelOptions
from mjx_morph.run import (Callback, Experiment, RunConfig, RunDir, compose_run_config, default_callbacks,
                           distributed, make_env_for, train, train_robots, use_compile_cache)
from mjx_morph.ppo.trainer import device_mesh
from multi_device_run import TINY, ppo_config, toy_trainer

ITERS = 4
ARCH = "metamorph"


class Final(Callback):
    """Keeps the train state the loop ends with."""

    def on_stop(self, loop, state, reason):
        self.state = state


def save_params(path: Path, ts) -> None:
    np.savez(path, *[np.asarray(x) for x in jax.tree.leaves(ts.params)])


def run_config(run_dir: Path, **kw) -> RunConfig:
    """The run of the trainer below as a RunConfig (the loop's keys; `train` is given the trainer itself)."""
    return RunConfig(**{**dict(ppo=ppo_config(), total_steps=ppo_config().steps_per_iter * ITERS, run_dir=str(run_dir),
                               checkpoint_every=2, fast_compile=True, compile_cache=None, model=ModelOptions(**TINY)),
                        **kw})


def non_local_arrays(obj, path: str = "env", seen: set | None = None) -> list[str]:
    """Paths of the jax.Arrays reachable from `obj` (attributes, containers, pytrees) that this process cannot
    address."""
    seen = set() if seen is None else seen
    if id(obj) in seen or isinstance(obj, (str, bytes, int, float, type, np.ndarray)) or obj is None:
        return []
    seen.add(id(obj))
    if isinstance(obj, jax.Array):
        return [] if obj.is_fully_addressable else [path]
    if isinstance(obj, dict):
        items = obj.items()
    elif isinstance(obj, (list, tuple)):
        items = enumerate(obj)
    elif hasattr(obj, "__dataclass_fields__"):
        items = ((k, getattr(obj, k)) for k in obj.__dataclass_fields__)
    elif hasattr(obj, "__dict__"):
        items = vars(obj).items()
    else:
        return []
    return [p for k, v in items for p in non_local_arrays(v, f"{path}.{k}", seen)]


def main(out: Path) -> None:
    assert distributed.initialize()               # from the environment
    use_compile_cache(os.environ.get("MJX_MORPH_XLA_CACHE"), min_compile_s=1.0)
    me, procs = jax.process_index(), jax.process_count()
    info = {"process": me, "processes": procs, "devices": len(jax.devices()), "local": len(jax.local_devices())}
    trainer = toy_trainer(ARCH, devices=None, total_steps=ppo_config().steps_per_iter * ITERS)
    info["mesh"] = trainer.num_devices
    smoke = compose_run_config(["preset=smoke", "robots=gen/train"])
    info["non_local"] = non_local_arrays(make_env_for(smoke, train_robots(smoke)[1][:1]))
    info["mesh_of_2"] = [d.process_index for d in device_mesh(2, 8).devices.flat]     # one device of each process
    try:
        device_mesh(3, 12)
    except ValueError as e:
        info["mesh_of_3"] = str(e)

    # 1. the trainer alone
    ts = trainer.init(jax.random.PRNGKey(0))
    rows = []
    for _ in range(ITERS):
        ts, m = trainer.iteration(ts)
        rows.append({k: float(v) for k, v in jax.device_get(m).items()})
    info["loss"] = [r["loss"] for r in rows]
    h = ts.first
    info["shards"] = [len(h.sharding.device_set), len(h.addressable_shards)]
    save_params(out / f"direct_{me}.npz", ts)

    # 2. through train(): a checkpoint at 2, a resume to 4
    cfg = run_config(out / "run")
    exp = Experiment(cfg, "toy", (), trainer.env, trainer.model, trainer)
    train(run_config(out / "run", stop_after=2), exp)
    final = Final()
    train(cfg, exp, callbacks=[*default_callbacks(cfg), final])
    save_params(out / f"train_{me}.npz", final.state)
    info["iteration"] = int(final.state.iteration)

    # 3. process 0 alone reads the checkpoint back (evaluation), the others wait
    if distributed.is_main():
        run = RunDir(out / "run")
        got = run.restore(run.latest_step(), trainer.abstract_state())
        run.close()
        info["reader_diff"] = max(float(np.abs(np.asarray(a) - np.asarray(b)).max())
                                  for a, b in zip(jax.tree.leaves(got.params), jax.tree.leaves(final.state.params)))
    distributed.barrier("read back")
    info["agree"] = distributed.agree(me == 0)        # process 0's value everywhere
    print(json.dumps(info), flush=True)


if __name__ == "__main__":
    main(Path(sys.argv[1]))
