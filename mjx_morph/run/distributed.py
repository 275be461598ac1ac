"""One run over several processes (hosts): `jax.distributed` set up from the run's config or the environment, and
which process does what.

    initialize(cfg)     # at the start of train(), before any JAX computation; idempotent
    several()           # this process is one of several (jax.distributed started)
    is_main()           # process 0 (or the only one): the one that writes metrics, TensorBoard, figures, prints and
                        # evaluates
    print_main(...)     # print() on process 0 only
    agree(flag)         # process 0's value of a Python bool, on every process (the loop's decisions)
    barrier(name)       # wait until every process gets here

Settings: three RunConfig keys, each falling back to an environment variable when unset (null):

| key             | environment variable      | meaning                                                    |
|-----------------|---------------------------|------------------------------------------------------------|
| `coordinator`   | `MJX_MORPH_COORDINATOR`   | "host:port" of process 0 (the same on every process), or "auto" |
| `num_processes` | `MJX_MORPH_NUM_PROCESSES` | how many processes take part                               |
| `process_id`    | `MJX_MORPH_PROCESS_ID`    | this process, 0 .. num_processes - 1                       |

None of them set: one process, nothing is initialised. A coordinator address needs the other two. "auto" leaves the
settings to `jax.distributed.initialize`'s own detection (SLURM, Open MPI, Cloud TPU); num_processes and process_id
may then still be given. Either of them without a coordinator is an error. If the caller has initialised
`jax.distributed` itself, that is used (and given settings must agree with it).

The processes form one JAX program: `jax.devices()` lists every process's devices, the trainer's mesh spans them
all, and the jitted functions are the same global program on every process (ppo/trainer.py). The run directory must
be on a file system every process sees (Orbax writes each process's shards of the checkpoint there). On CPUs the
processes' collectives go through gloo, JAX's default (`jax_cpu_collectives_implementation`): tests/test_multihost.py
runs two processes on loopback that way. Several processes count only once jax.distributed has started: on a TPU
pod, say, use coordinator=auto so that only process 0 writes.
"""
from __future__ import annotations

import os
import re
from typing import Any, NamedTuple, Optional

import jax
import numpy as np

#: the environment variable of each setting
ENV = {"coordinator": "MJX_MORPH_COORDINATOR", "num_processes": "MJX_MORPH_NUM_PROCESSES",
       "process_id": "MJX_MORPH_PROCESS_ID"}
AUTO = "auto"


class Settings(NamedTuple):
    coordinator: str                   # "host:port", or "auto"
    num_processes: Optional[int]       # None only with "auto" (JAX detects it)
    process_id: Optional[int]


def _get(cfg: Any, key: str, env: dict) -> tuple[Any, str]:
    """(value, where it came from: "key=value" for messages) of one setting: the config key, else its variable."""
    v = getattr(cfg, key, None) if cfg is not None else None
    if v is not None:
        return v, f"{key}={v}"
    raw = env.get(ENV[key])
    if raw is None or raw.strip() == "":
        return None, ""
    where = f"${ENV[key]}={raw!r}"
    if key == "coordinator":
        return raw.strip(), where
    try:
        return int(raw), where
    except ValueError:
        raise ValueError(f"{where}: expected an integer (the {key.replace('_', ' ')})") from None


def settings(cfg: Any = None, env: dict | None = None) -> Settings | None:
    """The distributed settings of `cfg` (a RunConfig, or anything with the three attributes; None: none) with the
    environment's as fallback; None for a single process. Half-given settings raise ValueError naming the key."""
    env = os.environ if env is None else env
    coord, c_where = _get(cfg, "coordinator", env)
    n, n_where = _get(cfg, "num_processes", env)
    pid, p_where = _get(cfg, "process_id", env)
    if coord is None:
        given = n_where or p_where
        if given:
            raise ValueError(f"{given} given without coordinator: set coordinator=host:port (or ${ENV['coordinator']}"
                             f"), the address of process 0, or coordinator=auto on a cluster JAX detects")
        return None
    if coord != AUTO and not re.fullmatch(r"\S+:\d+", coord):
        raise ValueError(f"{c_where}: expected host:port (process 0's address and a free port) or auto")
    if n is not None and n < 1:
        raise ValueError(f"{n_where}: expected a positive number of processes")
    if coord != AUTO:
        for key, v in (("num_processes", n), ("process_id", pid)):
            if v is None:
                raise ValueError(f"{c_where} needs {key} too ({key}=... or ${ENV[key]}) on every process")
    if pid is not None and (pid < 0 or (n is not None and pid >= n)):
        raise ValueError(f"{p_where}: expected 0 to {n - 1 if n is not None else 'num_processes - 1'}"
                         + (f" ({n_where})" if n is not None else ""))
    return Settings(coord, n, pid)


def initialize(cfg: Any = None) -> bool:
    """Start `jax.distributed` with the settings of `cfg` / the environment (`settings`), once per process; True
    when this process is one of several (or jax.distributed was started by the caller). Must run before any JAX
    computation of the process: the process's device list is fixed then."""
    s = settings(cfg)
    if jax.distributed.is_initialized():
        if s is not None:
            for key, have in (("num_processes", jax.process_count()), ("process_id", jax.process_index())):
                want = getattr(s, key)
                if want is not None and want != have:
                    raise ValueError(f"{key}={want}: this process already runs as {key}={have} "
                                     "(jax.distributed was initialised before)")
        return True
    if s is None:
        return False
    kwargs = {} if s.coordinator == AUTO else {"coordinator_address": s.coordinator}
    kwargs.update({k: v for k, v in (("num_processes", s.num_processes), ("process_id", s.process_id))
                   if v is not None})
    try:
        jax.distributed.initialize(**kwargs)
    except RuntimeError as e:
        if "must be called before" in str(e):
            raise RuntimeError(f"coordinator={s.coordinator}: several processes must be set up before any JAX "
                               "computation of the process (here JAX had already started: call "
                               "mjx_morph.run.distributed.initialize(cfg) first, before building an Experiment)"
                               ) from None
        raise
    except ValueError as e:     # "auto" where JAX recognises no cluster
        raise ValueError(f"coordinator={s.coordinator}: JAX found no cluster settings ("
                         f"{str(e).strip().splitlines()[0]}); give coordinator=host:port, num_processes and "
                         "process_id") from None
    return True


def several() -> bool:
    """This process is one of several (jax.distributed started). Asks JAX nothing before that, so it may be
    called before `initialize`."""
    return jax.distributed.is_initialized() and jax.process_count() > 1


def is_main() -> bool:
    """Process 0 of several, or the only process."""
    return not several() or jax.process_index() == 0


def print_main(*args, **kwargs) -> None:
    """print() on process 0 only."""
    if is_main():
        print(*args, **kwargs)


def agree(flag: bool) -> bool:
    """Process 0's `flag` on every process (every process must call it at the same point): decisions that each
    process would take from its own clock, such as a time limit, are taken once."""
    if not several():
        return bool(flag)
    from jax.experimental import multihost_utils
    return bool(multihost_utils.broadcast_one_to_all(np.asarray(bool(flag))))


_passed: dict[str, int] = {}      # barriers passed, by name


def barrier(name: str, timeout_s: float = 24 * 3600.0) -> None:
    """Wait until every process has reached barrier `name` (as often as this one has), at most `timeout_s`: a wait
    on the coordinator, not a device collective, so it may be long (process 0 evaluating, say)."""
    if not several():
        return
    _passed[name] = _passed.get(name, 0) + 1
    name = f"{name} #{_passed[name]}"
    from jax._src import distributed as jax_distributed      # the coordinator client jax.distributed started
    jax_distributed.global_state.client.wait_at_barrier(f"mjx_morph:{name}", int(timeout_s * 1000))
