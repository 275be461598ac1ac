"""Data parallel over devices (`devices=N`, mjx_morph/ppo/trainer.py): N devices run the algorithm of one device with
the same global batch. Checked on N = 4 virtual CPU devices in a fresh process (the device count is fixed when JAX
starts): after 3 iterations of R-MoMo and MetaMorph, parameters and env states equal the 1-device run's up to the
order of summation, and the env axis is really spread over the 4 devices. The iterations run as a run takes them by
default (rollout and update, two jitted calls), so the update's compiled text is read without compiling it again
(docs/benchmarks.md, "CPU notes"); the fused iteration over several devices is tests/test_multihost.py's."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from mjx_morph.ppo.trainer import device_mesh

HERE = Path(__file__).resolve().parent
#: parameters after 3 iterations (2 epochs x 4 minibatches each, Adam lr 3e-4 warming up): reassociated float32
#: sums; measured 3e-8 (rmomo) and 1.5e-8 (metamorph)
PARAM_TOLERANCE = 1e-6


@pytest.fixture(scope="module")
def four_devices():
    env = {**os.environ, "XLA_FLAGS": f"{os.environ['XLA_FLAGS']} --xla_force_host_platform_device_count=4",
           "JAX_PLATFORMS": "cpu",
           "PYTHONPATH": os.pathsep.join([str(HERE), str(HERE.parent), os.environ.get("PYTHONPATH", "")])}
    p = subprocess.run([sys.executable, str(HERE / "multi_device_run.py"), "4"], env=env, capture_output=True,
                       text=True, timeout=900)
    assert p.returncode == 0, p.stderr[-3000:]
    return json.loads(p.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("arch", ["rmomo", "metamorph"])
def test_four_devices_equal_one_device(four_devices, arch):
    r = four_devices[arch]
    assert r["shards"] == [1, 4]
    assert r["minibatches"] == r["minibatches_n"] and min(r["minibatches"]) > 0
    assert r["env_diff"] < 1e-4, r
    assert 0 < max(abs(a) for a in r["loss"])
    assert r["param_diff"] < PARAM_TOLERANCE, r


@pytest.mark.parametrize("arch", ["rmomo", "metamorph"])
def test_update_is_data_parallel(four_devices, arch):
    """On several devices each computes its own blocks of a minibatch (ppo.minibatch_blocks, and batch-major rows
    in the networks): the compiled update moves no minibatch between devices, only the gradients and loss
    statistics: all-reduces of at most the parameters, the per-robot tables the hypernetworks generate from them
    (R-MoMo: XLA sums their gradients before the hypernetwork's backward) and a few scalars. Before, every device
    gathered the whole minibatch and computed the update in full (docs/benchmarks.md, "Several devices")."""
    r = four_devices[arch]
    ops = r["collectives"]
    assert ops and all(op == "all-reduce" for op, _ in ops), ops
    assert sum(n for _, n in ops) <= r["params"] + r["tables"] + 64, (ops, r["params"], r["tables"])


def test_seeds_spread_over_devices(four_devices):
    """seeds=2 on 4 devices: a ("seed", "env") mesh of 2 x 2, each seed equal to that seed alone on one device
    (both with 4 blocks of envs per minibatch)."""
    r = four_devices["seeds"]
    assert r["mesh"] == {"seed": 2, "env": 2} and r["shards"] == 4
    assert r["param_diff"] < PARAM_TOLERANCE, r


def test_device_count_errors():
    with pytest.raises(ValueError, match="devices=3: expected 1 to 1"):
        device_mesh(3, 8)
    assert device_mesh(None, 8) is None and device_mesh(1, 8) is None   # one visible device: no mesh
