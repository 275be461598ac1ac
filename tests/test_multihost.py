"""Several processes (`mjx_morph/run/distributed.py`): two processes on loopback, each with 2 virtual CPU devices
(gloo collectives), train one run over the 4 devices (tests/multi_process_run.py). Both end with the same
parameters, equal to one process on one device with the same global batch; through `train()` only process 0 logs
and prints, the checkpoint it wrote resumes on both processes and on this single-device process; the MJX env keeps
its arrays on each process's own device. The settings' errors."""
from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from mjx_morph.run import Callback, Experiment, RunDir, default_callbacks, distributed, train
from mjx_morph.run.distributed import settings
from multi_device_run import ppo_config, toy_trainer
from multi_process_run import ARCH, ITERS, Final, run_config
from test_devices import PARAM_TOLERANCE

HERE = Path(__file__).resolve().parent
PROCESSES = 2


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def two_processes(tmp_path_factory):
    """Runs tests/multi_process_run.py as processes 0 and 1 of one run: (out folder, [JSON of each], [stdout],
    [stderr])."""
    out = tmp_path_factory.mktemp("multihost")
    port = free_port()
    base = {**os.environ, "XLA_FLAGS": f"{os.environ['XLA_FLAGS']} --xla_force_host_platform_device_count=2",
            "JAX_PLATFORMS": "cpu",
            "PYTHONPATH": os.pathsep.join([str(HERE), str(HERE.parent), os.environ.get("PYTHONPATH", "")]),
            "MJX_MORPH_COORDINATOR": f"127.0.0.1:{port}", "MJX_MORPH_NUM_PROCESSES": str(PROCESSES)}
    procs = [subprocess.Popen([sys.executable, str(HERE / "multi_process_run.py"), str(out)],
                              env={**base, "MJX_MORPH_PROCESS_ID": str(i)}, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for i in range(PROCESSES)]
    try:
        outs = [p.communicate(timeout=600) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    assert all(p.returncode == 0 for p in procs), "\n".join(
        f"process {i} (exit {p.returncode}): {e[-2000:]}" for i, (p, (_, e)) in enumerate(zip(procs, outs)))
    infos = [json.loads(o.strip().splitlines()[-1]) for o, _ in outs]
    return out, infos, [o for o, _ in outs], [e for _, e in outs]


@pytest.fixture(scope="module")
def one_device():
    """The same run on this process's one device: (trainer, its parameters after every iteration). Its minibatches
    are those of the 4 devices of the two processes: 4 blocks of envs (ppo.minibatch_blocks)."""
    trainer = toy_trainer(ARCH, devices=1, total_steps=ppo_config().steps_per_iter * ITERS, blocks=4)
    ts = trainer.init(jax.random.PRNGKey(0))
    params = []
    for _ in range(ITERS):
        ts, _ = trainer.iteration(ts)
        params.append(ts.params)
    return trainer, params


def npz(path: Path) -> list[np.ndarray]:
    with np.load(path) as f:
        return [f[k] for k in sorted(f.files, key=lambda k: int(k.split("_")[1]))]


def max_diff(a, b) -> float:
    a, b = jax.tree.leaves(a), jax.tree.leaves(b)
    assert len(a) == len(b)
    return max(float(np.abs(np.asarray(x) - np.asarray(y)).max()) for x, y in zip(a, b))


def test_two_processes_share_one_run(two_processes):
    _, infos, _, _ = two_processes
    for i, info in enumerate(infos):
        assert (info["process"], info["processes"], info["devices"], info["local"], info["mesh"]) == (i, 2, 4, 2, 4)
        assert info["shards"] == [4, 2]           # the env axis over all 4 devices, 2 of them this process's
        assert info["mesh_of_2"] == [0, 1]        # devices=2: one device of each process
        assert info["non_local"] == []            # the MJX model and data template are on this process's device
        assert info["mesh_of_3"].startswith("devices=3: expected a multiple of the 2 processes")
        assert info["iteration"] == ITERS and info["agree"] is True
    assert infos[0]["loss"] == infos[1]["loss"] and 0 < max(abs(x) for x in infos[0]["loss"])


def test_both_processes_end_like_one_device(two_processes, one_device):
    out, _, _, _ = two_processes
    _, params = one_device
    direct = [npz(out / f"direct_{i}.npz") for i in range(PROCESSES)]
    trained = [npz(out / f"train_{i}.npz") for i in range(PROCESSES)]
    assert max_diff(direct[0], direct[1]) == 0.0 and max_diff(trained[0], trained[1]) == 0.0   # replicated
    assert max_diff(direct[0], params[-1]) < PARAM_TOLERANCE
    assert max_diff(trained[0], params[-1]) < PARAM_TOLERANCE     # resumed, and rollout and update jitted apart


def test_only_process_zero_logs_and_prints(two_processes):
    out, infos, stdouts, stderrs = two_processes
    run = out / "run"
    assert [int(r["iteration"]) for r in RunDir(run).read_metrics()] == [1, 2, 3, 4]    # logged once, not twice
    assert (run / "learning_curve.png").exists() and (run / "config.yaml").exists()
    assert "[mjx_morph] resumed from" in stdouts[0] and "[mjx_morph]" not in stdouts[1]
    assert "it/s" in stderrs[0] and "it/s" not in stderrs[1]                            # the progress bar
    assert RunDir(run).steps() == [2, 4]
    assert infos[0]["reader_diff"] == 0.0 and "reader_diff" not in infos[1]      # process 0 read it back alone


def test_checkpoint_of_two_processes_resumes_on_one_device(two_processes, one_device, tmp_path):
    """The checkpoint at iteration 2 of 2 processes x 2 devices, resumed by this process on one device."""
    out, _, _, _ = two_processes
    trainer, params = one_device
    d = tmp_path / "run"
    shutil.copytree(out / "run", d)
    cfg = run_config(d, resume_step=2, progress=False, phase_timing=False)
    final = Final()
    train(cfg, Experiment(cfg, "toy", (), trainer.env, trainer.model, trainer),
          callbacks=[*default_callbacks(cfg), final])
    assert int(final.state.iteration) == ITERS
    assert max_diff(final.state.params, params[-1]) < PARAM_TOLERANCE
    assert max_diff(final.state.params, npz(out / "train_0.npz")) < PARAM_TOLERANCE
    assert [int(r["iteration"]) for r in RunDir(d).read_metrics()] == [1, 2, 3, 4]


class Cfg:
    def __init__(self, coordinator=None, num_processes=None, process_id=None):
        self.coordinator, self.num_processes, self.process_id = coordinator, num_processes, process_id


def test_settings_from_config_or_environment():
    assert settings(Cfg(), env={}) is None                                        # one process
    assert settings(Cfg("10.0.0.1:1234", 2, 1), env={}) == ("10.0.0.1:1234", 2, 1)
    env = {"MJX_MORPH_COORDINATOR": "h:5", "MJX_MORPH_NUM_PROCESSES": "4", "MJX_MORPH_PROCESS_ID": "3"}
    assert settings(Cfg(), env=env) == ("h:5", 4, 3)
    assert settings(Cfg(process_id=0), env=env) == ("h:5", 4, 0)                   # the key wins
    assert settings(Cfg("auto"), env={}) == ("auto", None, None)                   # JAX detects the rest


@pytest.mark.parametrize("cfg, env, error", [
    (Cfg(num_processes=2), {}, r"^num_processes=2 given without coordinator"),
    (Cfg(), {"MJX_MORPH_PROCESS_ID": "1"}, r"^\$MJX_MORPH_PROCESS_ID='1' given without coordinator"),
    (Cfg("h:5", 2), {}, r"^coordinator=h:5 needs process_id too"),
    (Cfg("h:5", process_id=0), {}, r"^coordinator=h:5 needs num_processes too"),
    (Cfg("h", 2, 0), {}, r"^coordinator=h: expected host:port"),
    (Cfg("h:5", 2, 2), {}, r"^process_id=2: expected 0 to 1 \(num_processes=2\)"),
    (Cfg("h:5", 0, 0), {}, r"^num_processes=0: expected a positive number"),
    (Cfg("h:5", 2), {"MJX_MORPH_PROCESS_ID": "one"}, r"^\$MJX_MORPH_PROCESS_ID='one': expected an integer"),
])
def test_half_given_settings_name_the_key(cfg, env, error):
    with pytest.raises(ValueError, match=error):
        settings(cfg, env=env)


def test_single_process_and_late_start():
    """No settings: nothing starts (this process is the main one); settings after JAX has started are refused."""
    jax.devices()
    assert distributed.initialize(Cfg()) is False and distributed.is_main() and distributed.agree(True)
    with pytest.raises(RuntimeError, match=r"coordinator=127.0.0.1:1: several processes must be set up before"):
        distributed.initialize(Cfg("127.0.0.1:1", 2, 0))
