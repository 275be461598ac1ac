"""The training command end to end on CPU with the real MJX env (2 generated robots, tiny networks):
smoke runs, run directory contents, resume equivalence, and clear errors for bad configs and checkpoints."""
from __future__ import annotations

import json
import math
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
import yaml

from mjx_morph.run import Callback, RunDir, RunDirError, build, default_callbacks, train, use_compile_cache

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "experiments" / "conf"


from conftest import smoke_config as config


def params_of(run_dir: Path, trainer):
    run = RunDir(run_dir)
    ts = run.restore(run.latest_step(), trainer.abstract_state())
    run.close()
    return ts


@pytest.fixture(scope="module")
def full_run(smoke_run):
    return smoke_run


@pytest.fixture(scope="module")
def exp(smoke_run):
    """The smoke config's Experiment, shared so that its compiled functions serve every test of this module."""
    return build(smoke_run[1])


def test_smoke_run_writes_everything(full_run):
    d, cfg = full_run
    assert {"config.yaml", "metrics.csv", "learning_curve.png", "tb", "checkpoints"} <= {p.name for p in d.iterdir()}
    rows = RunDir(d).read_metrics()
    assert [int(r["iteration"]) for r in rows] == [1, 2, 3]
    # the first minibatch after a rollout recomputes what the rollout acted with: ratio 1, KL 0. In the first
    # iteration exactly (the tail is all resets); later the acting state and the training window both burn in over
    # the stored tail, in two compiled programs whose float32 rounding differs on a CPU: R-MoMo's smoke run reads
    # 3.5e-5 and 1.1e-4 in iterations 2 and 3 (8.1e-5 without fast compilation), the feed-forward models <= 5e-8,
    # and the paper runs on GPUs <= 6e-8 (session 42)
    assert abs(rows[0]["first_ratio"] - 1) < 1e-6 and abs(rows[0]["first_kl"]) < 1e-6
    for r in rows:
        assert abs(r["first_ratio"] - 1) < 5e-4 and abs(r["first_kl"]) < 5e-4
        assert np.isfinite(r["loss"]) and r["sps"] > 0 and r["instabilities"] == 0
    assert any(f.name.startswith("events") for f in (d / "tb").iterdir())
    assert (d / "learning_curve.png").stat().st_size > 5000
    [entry] = yaml.safe_load((d / "devices.yaml").read_text())      # one invocation, on this machine's devices
    dev = jax.devices()[0]
    assert entry["start_iteration"] == 0 and entry["device_kind"] == dev.device_kind
    assert entry["platform"] == dev.platform and entry["num_devices"] >= 1 and entry["processes"] == 1
    assert entry["started"].endswith("+00:00")                         # ISO time, UTC
    assert entry["jax"] == jax.__version__ and entry["platform_version"] == dev.client.platform_version
    assert len(entry["topology"]) == 16 and int(entry["topology"], 16) >= 0     # the cache key's device fingerprint


def test_interrupted_and_resumed_run_ends_like_uninterrupted(full_run, exp, tmp_path):
    d_full, cfg = full_run
    d = tmp_path / "resumed"
    seen = Recorder()
    train(config(f"run_dir={d}", "stop_after=2"), exp, callbacks=[*default_callbacks(cfg), seen])
    assert RunDir(d).latest_step() == 2
    assert seen.events == [("start", 0, 2), ("iteration", 1), ("iteration", 2), ("stop", "done", 2)]
    train(config(f"run_dir={d}"), exp)
    a, b = params_of(d_full, exp.trainer), params_of(d, exp.trainer)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert [int(r["iteration"]) for r in RunDir(d).read_metrics()] == [1, 2, 3]
    invocations = yaml.safe_load((d / "devices.yaml").read_text())  # the resume appended its own entry
    assert [e["start_iteration"] for e in invocations] == [0, 2]
    assert {e["device_kind"] for e in invocations} == {jax.devices()[0].device_kind}
    assert len({(e["platform_version"], e["topology"]) for e in invocations}) == 1   # one machine: one cache key


class CtrlC(Callback):
    """Sends this process Ctrl-C (SIGINT) after iteration `at`, and again (twice, as the device tool's `timeout`
    does) when the run stops, before the checkpoint callback after it writes the last checkpoint."""

    def __init__(self, at: int):
        self.at = at

    def on_iteration(self, loop, state, row):
        if row["iteration"] == self.at:
            os.kill(os.getpid(), signal.SIGINT)

    def on_stop(self, loop, state, reason):
        os.kill(os.getpid(), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGINT)


def test_ctrl_c_saves_a_checkpoint_and_a_second_one_waits_for_it(exp, tmp_path, capsys):
    """Ctrl-C ends the invocation with a checkpoint (reason "interrupted"); Ctrl-C again while the run stops is held
    until that checkpoint is written, then raised; the run resumes from it."""
    from mjx_morph.run.loop import Checkpoints, MetricsLog
    d, seen = tmp_path / "interrupted", Recorder()
    before = signal.signal(signal.SIGINT, signal.default_int_handler)   # a pytest-xdist worker may ignore SIGINT
    try:
        with pytest.raises(KeyboardInterrupt):
            train(config(f"run_dir={d}", "checkpoint_every=100"), exp,
                  callbacks=[MetricsLog(), seen, CtrlC(at=1), Checkpoints(100)])
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler       # restored after the hold
    finally:
        signal.signal(signal.SIGINT, before)
    assert seen.events == [("start", 0, 3), ("iteration", 1), ("stop", "interrupted", 1)]
    assert RunDir(d).latest_step() == 1
    err = capsys.readouterr().err
    assert err.count("Ctrl-C: held until the last checkpoint is written") == 1
    assert "interrupted at iteration 1; checkpoint saved" in err
    train(config(f"run_dir={d}"), exp)
    assert [int(r["iteration"]) for r in RunDir(d).read_metrics()] == [1, 2, 3]


def test_a_run_that_starts_broken_stops_with_a_checkpoint_and_is_not_resumed(exp, tmp_path, capsys):
    """stop_unhealthy (default true): the first health warning ends the invocation (reason "unhealthy") with a
    checkpoint and the warning in unhealthy.txt; a rerun refuses the run, naming the file and the warning, and
    changes nothing; stop_unhealthy=false trains it on. (A check that always warns stands in for a broken run.)"""
    from mjx_morph.run import UNHEALTHY, HealthWarnings
    from mjx_morph.run.loop import Checkpoints, MetricsLog
    from mjx_morph.run.run_dir import RunDirError
    d, seen = tmp_path / "broken", Recorder()
    train(config(f"run_dir={d}", "checkpoint_every=100"), exp,
          callbacks=[MetricsLog(), seen, HealthWarnings(max_value=-1.0, stop=True), Checkpoints(100)])
    assert seen.events == [("start", 0, 3), ("iteration", 1), ("stop", "unhealthy", 1)]
    assert RunDir(d).latest_step() == 1
    assert "iteration 1's value estimates average" in (d / UNHEALTHY).read_text()
    cap = capsys.readouterr()
    assert "[mjx_morph] warning: iteration 1's value estimates" in cap.out
    assert "stopped at iteration 1: the run starts broken" in cap.err
    with pytest.raises(RunDirError, match=r"unhealthy.txt: this run stopped because it starts broken \(iteration 1"):
        train(config(f"run_dir={d}"), exp)
    assert [int(r["iteration"]) for r in RunDir(d).read_metrics()] == [1]
    train(config(f"run_dir={d}", "stop_unhealthy=false"), exp)
    assert [int(r["iteration"]) for r in RunDir(d).read_metrics()] == [1, 2, 3]


def test_run_moved_in_parts_resumes_like_uninterrupted(full_run, exp, tmp_path):
    """experiments.collect checkpoint=true part_mb=...: an unfinished run leaves its machine as parts of at most
    part_mb MiB (the newest checkpoint only), is joined elsewhere with cat | tar, and resumes there exactly."""
    import subprocess
    import tarfile
    from experiments import collect
    d_full, cfg = full_run
    study = tmp_path / "here" / "study"
    train(config(f"run_dir={study / 'moving'}", "stop_after=1", "checkpoint_every=1"), exp)
    train(config(f"run_dir={study / 'moving'}", "stop_after=1", "checkpoint_every=1"), exp)
    assert RunDir(study / "moving").steps() == [1, 2]
    out = tmp_path / "out" / "moving.tar.gz"
    big = max(f.stat().st_size for f in (study / "moving" / "checkpoints").rglob("*") if f.is_file())
    assert big > 10 * 2 ** 10      # over max_file_mb below: checkpoint files are never left out
    assert collect.main([f"runs=[{study}]", f"out={out}", "checkpoint=true", "part_mb=0.05",
                         "max_file_mb=0.01"]) == 0
    parts = sorted(out.parent.iterdir())
    assert len(parts) > 2 and [p.name for p in parts] == [f"moving.tar.gz.{i:03d}" for i in range(len(parts))]
    assert all(p.stat().st_size <= 0.05 * 2 ** 20 for p in parts)
    there = tmp_path / "there"
    there.mkdir()
    subprocess.run(f"cat {out}.* | tar xzf - -C {there}", shell=True, check=True)
    moved = there / "study" / "moving"
    assert RunDir(moved).steps() == [2]                         # the newest checkpoint alone
    assert (moved / "metrics.csv").read_bytes() == (study / "moving" / "metrics.csv").read_bytes()
    assert any((moved / "tb").iterdir())
    train(config(f"run_dir={moved}"), exp)
    for x, y in zip(jax.tree.leaves(params_of(d_full, exp.trainer)), jax.tree.leaves(params_of(moved, exp.trainer))):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert [int(r["iteration"]) for r in RunDir(moved).read_metrics()] == [1, 2, 3]
    # without checkpoint=true nothing of the checkpoint travels; parts need an archive
    assert collect.main([f"runs=[{study}]", f"out={tmp_path / 'small.tar.gz'}"]) == 0
    with tarfile.open(tmp_path / "small.tar.gz") as tar:
        assert not any("checkpoints" in n or "/tb/" in n for n in tar.getnames())
    with pytest.raises(ValueError, match="part_mb=1.0: parts are cut from an archive"):
        collect.collect(collect.CollectConfig(runs=[str(study)], out=str(tmp_path / "folder"), part_mb=1.0))


def test_stop_at_ends_the_run_for_good(full_run, exp, tmp_path):
    """stop_at=N ends the run at iteration N of its schedule; rerunning it trains no further (unlike stop_after).
    stop_at is free on resume: rerun with stop_at=null, the run trains on to its schedule's end and ends where the
    uninterrupted run does (a 20 M-step look, total_steps=1e8 stop_at=245, trained on to 100 M: docs/leases.md)."""
    d = tmp_path / "stop_at"
    for _ in range(2):
        train(config(f"run_dir={d}", "stop_at=1"), exp)
        assert RunDir(d).latest_step() == 1 and [int(r["iteration"]) for r in RunDir(d).read_metrics()] == [1]
    train(config(f"run_dir={d}", "stop_at=null"), exp)
    assert [int(r["iteration"]) for r in RunDir(d).read_metrics()] == [1, 2, 3]
    for x, y in zip(jax.tree.leaves(params_of(full_run[0], exp.trainer)), jax.tree.leaves(params_of(d, exp.trainer))):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


class Recorder(Callback):
    """Records what the loop reports to its callbacks."""

    def __init__(self):
        self.events = []

    def on_start(self, loop):
        self.events.append(("start", loop.start, loop.stop))

    def on_iteration(self, loop, state, row):
        assert int(state.iteration) == row["iteration"] and row["env_steps"] == row["iteration"] * 256
        self.events.append(("iteration", int(row["iteration"])))

    def on_stop(self, loop, state, reason):
        self.events.append(("stop", reason, int(state.iteration)))


def _listing(d: Path) -> dict:
    return {str(p.relative_to(d)): p.stat().st_size for p in sorted(d.rglob("*")) if p.is_file()}


def test_other_architecture_in_same_run_dir_is_refused(full_run, tmp_path):
    d = tmp_path / "copy"
    shutil.copytree(full_run[0], d)
    before = _listing(d)
    with pytest.raises(RunDirError, match=r"config.yaml: this run directory belongs to a different run \(arch"):
        train(config(f"run_dir={d}", "arch=metamorph"))
    assert _listing(d) == before


def test_corrupt_checkpoint_gives_clear_error_and_changes_nothing(full_run, exp, tmp_path):
    d = tmp_path / "corrupt"
    shutil.copytree(full_run[0], d)
    for f in (d / "checkpoints" / "3").rglob("*"):
        if f.is_file() and f.stat().st_size > 0:
            f.write_bytes(b"\0garbage" * 4)
    before = _listing(d)
    with pytest.raises(RunDirError, match=r"checkpoints/3: the checkpoint could not be restored") as e:
        train(config(f"run_dir={d}"), exp)
    assert _listing(d) == before
    msg = str(e.value)
    assert "\n" not in msg and "resume_step=2" in msg and "TensorStore" not in msg and "<" not in msg
    # the offered way out: resume from the previous checkpoint; the corrupt one is set aside, not deleted
    train(config(f"run_dir={d}", "resume_step=2"), exp)
    assert (d / "checkpoints.orphaned" / "3").is_dir() and RunDir(d).steps()[-1] == 3
    assert [int(r["iteration"]) for r in RunDir(d).read_metrics()] == [1, 2, 3]
    for x, y in zip(jax.tree.leaves(params_of(full_run[0], exp.trainer)), jax.tree.leaves(params_of(d, exp.trainer))):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_failed_start_writes_nothing(tmp_path):
    """Bad robots, values or directories fail before the run directory is touched (nothing to block a rerun)."""
    d = tmp_path / "p1"
    for bad in ("robots=typo", "num_robots=0", "num_robots=-1", "num_robots=500", "total_steps=-5",
                "ppo.num_envs=0", "ppo.epochs=0", "model.d_model=0"):
        with pytest.raises(Exception) as e:
            train(config(f"run_dir={d}", bad))
        assert not d.exists(), bad
        assert "\n" not in str(e.value) and str(e.value), bad
    with pytest.raises(ValueError, match=r"num_robots=500: expected 1 to 100"):
        build(config("num_robots=500"))
    with pytest.raises(ValueError, match=r"total_steps=-5: expected a positive number"):
        build(config("total_steps=-5"))
    (tmp_path / "afile").write_text("x")
    with pytest.raises(RunDirError, match=r"afile/run: cannot write the run directory"):
        RunDir(tmp_path / "afile" / "run", {"seed": 0}).create()


def test_crash_before_the_first_checkpoint_leaves_no_duplicate_rows(full_run, exp, tmp_path):
    d = tmp_path / "crashed"
    shutil.copytree(full_run[0], d)
    shutil.rmtree(d / "checkpoints")                       # as if the first run died before saving anything
    train(config(f"run_dir={d}"), exp)
    assert [int(r["iteration"]) for r in RunDir(d).read_metrics()] == [1, 2, 3]
    assert (d / "metrics.csv.orphaned").exists() and (d / "tb.orphaned").is_dir()
    events = [f for f in (d / "tb").iterdir() if f.name.startswith("events")]
    assert len(events) == 1


def test_resume_with_changed_training_keys(full_run, exp, tmp_path):
    """A changed training key is refused with the difference, unless allowed; an allowed change is recorded."""
    from mjx_morph.run import to_dict
    from mjx_morph.run.config import FREE, IDENTITY
    d = tmp_path / "changed"
    shutil.copytree(full_run[0], d)
    before = _listing(d)
    with pytest.raises(RunDirError, match=r"ppo.lr: saved 0.0003, now 0.001 \(allow_changes=\[ppo.lr\]"):
        train(config(f"run_dir={d}", "ppo.lr=1e-3"), exp)
    assert _listing(d) == before
    new = to_dict(config("total_steps=1024", "allow_changes=[total_steps]", f"run_dir={d}"))
    run = RunDir(d, new, IDENTITY, FREE, ("total_steps",))
    assert run.changes == ["total_steps: 768 -> 1024"]
    run.create()
    history = yaml.safe_load((d / "config_history.yaml").read_text())
    assert history[0]["changes"] == ["total_steps: 768 -> 1024"] and history[0]["iteration"] == 3
    assert yaml.safe_load((d / "config.yaml").read_text())["total_steps"] == 1024
    with pytest.raises(RunDirError, match=r"arch: saved 'rmomo', now 'metamorph'"):
        RunDir(d, {**new, "arch": "metamorph"}, IDENTITY, FREE, ("arch",))   # identity keys never change
    RunDir(d, {**new, "stop_after": 7}, IDENTITY, FREE)                        # loop keys change freely


def test_feed_forward_smoke_run(smoke_run_ff):
    rows = RunDir(smoke_run_ff[0]).read_metrics()
    assert len(rows) == 3 and all(abs(r["first_ratio"] - 1) < 1e-4 for r in rows)


def test_unknown_config_key_is_an_error():
    out = subprocess.run([sys.executable, "-m", "experiments.run", "preset=smoke", "no_such_key=1"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120, env={**os.environ, "HYDRA_FULL_ERROR": "0"})
    assert out.returncode != 0 and "no_such_key" in out.stderr


def test_compile_cache_is_written_and_read_by_a_second_process(tmp_path):
    """`compile_cache=` (experiments.run/evaluate) keeps compiled programs on disk: a first process writes an entry,
    a second one with the same program finds it (JAX counts persistent-cache hits) and writes nothing new."""
    prog = ("import sys, jax, jax.numpy as jnp\n"
            "from jax import monitoring\n"
            "from mjx_morph.run import use_compile_cache\n"
            "hits = []\n"
            "monitoring.register_event_listener(lambda e, **kw: hits.append(e) if 'cache_hits' in e else None)\n"
            "use_compile_cache(sys.argv[1], min_compile_s=0)\n"
            "jax.jit(lambda x: jnp.sin(x) @ x.T)(jnp.ones((8, 8))).block_until_ready()\n"
            "print('hits', len(hits))\n")
    cache = tmp_path / "xla"

    def run():
        out = subprocess.run([sys.executable, "-c", prog, str(cache)], cwd=ROOT, capture_output=True, text=True,
                             timeout=120)
        assert out.returncode == 0, out.stderr
        return int(out.stdout.split()[-1]), sorted(p.name for p in cache.iterdir())

    hits1, files1 = run()
    hits2, files2 = run()
    assert hits1 == 0 and files1, "the first process must write its compiled program"
    assert hits2 >= 1 and files2 == files1, "the second process must read it back"
    assert use_compile_cache(None) is None


def test_stall_watchdog_ends_a_stalled_process_and_spares_a_live_one():
    """An iteration past stall_min (and 20x the slowest) ends the process with exit status 75 and a message naming
    the rerun; a disarmed watchdog never fires. In a subprocess: the watchdog ends its process."""
    code = ("import sys, time; from mjx_morph.run.loop import StallWatchdog; w = StallWatchdog(0.002); "
            "w.arm(6, 0.001 if sys.argv[1] == 'stall' else 0.0); "
            "time.sleep(3) if sys.argv[1] == 'stall' else (w.disarm(), time.sleep(0.5)); print('survived')")
    stalled = subprocess.run([sys.executable, "-c", code, "stall"], capture_output=True, text=True, timeout=300)
    assert stalled.returncode == 75 and "survived" not in stalled.stdout
    assert "iteration 7 has run" in stalled.stderr and "looks stalled" in stalled.stderr
    live = subprocess.run([sys.executable, "-c", code, "live"], capture_output=True, text=True, timeout=300)
    assert live.returncode == 0 and "survived" in live.stdout, live.stderr[-2000:]


def test_progress_lines_without_the_bar(capsys):
    """progress=false: one plain line per `progress_every_min` (not per iteration; counted from the end of the
    compiling first iteration), after the last of the seeds side by side, with their mean return, the env steps/s of all seeds and the time left at the mean iteration time (the
    compiling first iteration left out); the default callbacks choose it, or nothing with progress_every_min=null."""
    from types import SimpleNamespace
    from mjx_morph.run import ProgressBar, ProgressLines, RunConfig
    now = [0.0]
    cb = ProgressLines(1.0, clock=lambda: now[0])
    loops = [SimpleNamespace(member=m, members=2, start=10, stop=20) for m in range(2)]
    cb.on_start(loops[0])
    cb.on_start(loops[1])
    for it, t in zip(range(11, 16), (100.0, 130.0, 150.0, 170.0, 190.0)):   # 100 s to compile, then 20-30 s each
        now[0] = t
        for m, loop in enumerate(loops):
            cb.on_iteration(loop, None, {"iteration": it, "env_steps": it * 1000, "episode_return": 10.0 * (m + 1),
                                         "sps": 50.0, "wall_s": 100.0 if it == 11 else t - now[0] + 20.0})
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("[mjx_morph] iteration")]
    assert lines == ["[mjx_morph] iteration 14/20: 14,000 env steps, return 15.0, 100 env steps/s, 2.0 min to "
                     "iteration 20"]
    callbacks = lambda **kw: [type(c) for c in default_callbacks(RunConfig(**kw))]
    assert ProgressBar in callbacks() and ProgressLines not in callbacks()
    assert ProgressLines in callbacks(progress=False)
    assert ProgressLines not in callbacks(progress=False, progress_every_min=None)


def test_health_warnings_flag_a_run_that_starts_broken(capsys):
    """A run whose first iterations look broken (session 44's R-MeMo: value estimates of 4.6e5 in iteration 1, one
    minibatch of 16 applied per iteration) gets one warning line per kind and run; a healthy one none, and a run
    resumed past its first iterations is not judged on them."""
    from types import SimpleNamespace
    from mjx_morph.run import HealthWarnings, RunConfig
    trainer = SimpleNamespace(num_minibatches=16, cfg=SimpleNamespace(epochs=8))
    loop = lambda m=0, n=1: SimpleNamespace(member=m, members=n, run=SimpleNamespace(path=Path(f"runs/s{m}")),
                                            experiment=SimpleNamespace(trainer=trainer))
    row = lambda it, value, mb: {"iteration": it, "value_mean": value, "minibatches": mb}
    warnings = lambda: [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("[mjx_morph] warning")]

    cb = HealthWarnings()
    for it in range(1, 8):
        cb.on_iteration(loop(), None, row(it, 0.5 * it, 128.0 if it == 1 else 40.0))
    assert warnings() == []
    cb = HealthWarnings()
    for it in range(1, 8):
        cb.on_iteration(loop(), None, row(it, 4.6e5, 1.0))
    out = warnings()
    assert len(out) == 2 and "iteration 1's value estimates average 4.6e+05" in out[0]
    assert "at most one minibatch run in each of the first 5 iterations" in out[1]
    cb = HealthWarnings()
    for it in range(1, 4):                              # two seeds side by side: each named, each warned once
        for m in range(2):
            cb.on_iteration(loop(m, 2), None, row(it, float("nan") if m else 1.0, 16.0))
    assert warnings() == ["[mjx_morph] warning (s1): iteration 1's value estimates average nan, where scaled returns "
                          "keep them within a few units: is a model input out of scale (contexts, observations)?"]
    cb = HealthWarnings()
    for it in range(4, 8):                              # resumed at iteration 4: its first 5 are not all seen
        cb.on_iteration(loop(), None, row(it, 1.0, 0.0))
    assert warnings() == []
    assert HealthWarnings in [type(c) for c in default_callbacks(RunConfig())]


def test_metrics_csv_keeps_float32_exactly_in_few_digits(tmp_path):
    """metrics.csv writes each metric as the shortest text that reads back as the same float32 (the learner's
    metrics are float32) and whole numbers as integers: half the bytes of float64's 17 digits, nothing lost."""
    import numpy as np
    run = RunDir(tmp_path / "r", {"seed": 0})
    run.create()
    row = {"iteration": 1, "env_steps": 81920, "approx_kl": np.float32(0.00867781788110733), "episodes": 589.0,
           "lr": 3.000000106112566e-05, "first_kl": np.float32(-3.632158e-09), "wall_s": 92.677149113,
           "loss": float("nan")}
    run.log(row)
    run.close()
    text = (tmp_path / "r" / "metrics.csv").read_text().splitlines()[1]
    assert text == "1,81920,0.008677818,589,3.0000001e-05,-3.632158e-09,92.67715,nan"
    back = RunDir(tmp_path / "r").read_metrics()[0]
    for k in ("approx_kl", "lr", "first_kl"):
        assert np.float32(back[k]) == np.float32(row[k]), k
    assert back["episodes"] == 589 and math.isnan(back["loss"]) and abs(back["wall_s"] - 92.677149113) < 1e-4


def test_eval_json_floats_keep_float32_precision():
    """eval/*.json store floats at float32's precision (shortest text), whole numbers and non-numbers as they were."""
    import numpy as np
    from mjx_morph.run.run_dir import at_float32
    tree = {"mean_return": 1891.3029393490808, "env_steps": 20070400.0, "per_robot": {"a": 0.1234567891234},
            "trace": [1e-9 / 3, 2, True, None], "ci": float("nan"), "set": "unimal100/test70"}
    out = at_float32(tree)
    assert json.dumps(out["mean_return"]) == "1891.303" and out["env_steps"] == 20070400.0
    assert np.float32(out["per_robot"]["a"]) == np.float32(0.1234567891234)
    assert out["trace"][1:] == [2, True, None] and json.dumps(out["trace"][0]) == "3.3333333e-10"
    assert math.isnan(out["ci"]) and out["set"] == "unimal100/test70"


def test_a_resume_onto_other_physics_is_refused_unless_allowed(full_run, exp, tmp_path):
    """devices.yaml records the env's model digest per invocation; a resume whose env simulates other numbers (here:
    the last entry's digest made another) is refused before anything is compiled or written, and goes on with
    allow_changes=[model_digest], recorded in config_history.yaml."""
    d = tmp_path / "physics"
    shutil.copytree(full_run[0], d)
    f = d / "devices.yaml"
    entries = yaml.safe_load(f.read_text())
    assert entries[-1]["model_digest"] == exp.env.digest and len(exp.env.digest) == 16
    assert entries[-1]["cholesky"] == "jax"         # env.linalg=auto on a CPU: what MJX ran with, recorded
    entries[-1]["model_digest"] = "0123456789abcdef"
    f.write_text(yaml.safe_dump(entries, sort_keys=False))
    before = _listing(d)
    with pytest.raises(RunDirError, match=r"devices.yaml: the robots now compile to other physics than this run "
                                          rf"trained on \(model digest 0123456789abcdef from iteration 0 on, now "
                                          rf"{exp.env.digest}\).*allow_changes=\[model_digest\]"):
        train(config(f"run_dir={d}"), exp)
    assert _listing(d) == before
    train(config(f"run_dir={d}", "allow_changes=[model_digest]"), exp)
    history = yaml.safe_load((d / "config_history.yaml").read_text())
    assert history[-1]["changes"] == [f"model_digest: '0123456789abcdef' -> '{exp.env.digest}'"]
    assert yaml.safe_load(f.read_text())[-1]["model_digest"] == exp.env.digest
    train(config(f"run_dir={d}"), exp)                      # the physics it trains on now: no change to accept
    f.write_text("- [unclosed\n")
    with pytest.raises(RunDirError, match=r"devices.yaml: unreadable \(ParserError at line 2\).*move it aside") as e:
        train(config(f"run_dir={d}"), exp)
    assert "\n" not in str(e.value)


def test_expect_physics_stops_a_run_on_other_physics_before_anything_is_written(full_run, exp, tmp_path):
    """`expect_physics=<digest prefix>` (the seeds of a comparison): a config that builds other physics stops with
    the digest it builds, before compiling or writing; the matching prefix trains (here: resumes a finished run);
    a value that is not 8-16 hex digits is refused by the config's check."""
    d = tmp_path / "expect"
    shutil.copytree(full_run[0], d)
    before = _listing(d)
    with pytest.raises(ValueError, match=rf"expect_physics=0123456789abcdef: this config builds other physics, "
                                         rf"model digest {exp.env.digest} \(task ft.*nothing was written"):
        train(config(f"run_dir={d}", "expect_physics=0123456789abcdef"), exp)
    assert _listing(d) == before
    train(config(f"run_dir={d}", f"expect_physics={exp.env.digest[:8]}"), exp)
    assert len(yaml.safe_load((d / "devices.yaml").read_text())) == 2       # it ran (a resume with nothing to do)
    for bad in ("abc", "0123456789ABCDEF", "0123456789abcdef0"):
        with pytest.raises(ValueError, match=rf"expect_physics={bad}: expected 8 to 16 lowercase hex digits"):
            config(f"expect_physics={bad}").check()

def test_the_digest_tool_checks_a_runs_physics_and_records_it_only_where_none_was(full_run, exp, tmp_path, capsys):
    """`python -m experiments.digest`: the digest this checkout builds for a run's config against the one the run
    recorded (exit status 1 when they differ: this checkout would not resume it); for a run that recorded none,
    record=WHY writes it to physics.yaml with the checkout's commit and the reason, and never for a run with its own
    record; the report then reads it as computed."""
    from experiments import digest
    from mjx_morph.eval.runs import read_run
    from mjx_morph.run.run_dir import read_computed_physics, write_computed_physics
    ours, other = tmp_path / "runs" / "ours", tmp_path / "runs" / "old"
    shutil.copytree(full_run[0], ours, ignore=shutil.ignore_patterns("checkpoints", "tb"))
    shutil.copytree(ours, other)
    (other / "devices.yaml").unlink()                       # trained before runs recorded their physics
    assert digest.main([f"runs=[{tmp_path / 'runs'}]"]) == 0
    out = capsys.readouterr().out
    assert f"{ours}: recorded {exp.env.digest}; this checkout {exp.env.digest}: the same physics" in out
    assert f"{other}: recorded none; this checkout {exp.env.digest} (record=WHY writes" in out
    assert not (other / "physics.yaml").exists() and read_run(other).physics_computed is None

    why = "its code's sim: this one's (abc..HEAD)"
    assert digest.main([f"runs=[{tmp_path / 'runs'}]", f'record="{why}"']) == 0
    written = read_computed_physics(other)
    assert written["model_digest"] == exp.env.digest and written["why"] == why
    assert len(written["code"].split("+")[0]) in (40, 7)        # a commit ('unknown' outside git: 7 letters)
    assert not (ours / "physics.yaml").exists()             # its own record stands
    assert read_run(other).physics_computed == exp.env.digest and read_run(ours).physics_computed is None
    assert write_computed_physics(other, exp.env.digest, "again", "x") is False     # already says so
    with pytest.raises(RunDirError, match=r"physics.yaml: names .* this checkout computes 0123456789abcdef"):
        write_computed_physics(other, "0123456789abcdef", "why", "x")
    with pytest.raises(RunDirError, match=r"devices.yaml: the run recorded its physics .* Nothing was written"):
        write_computed_physics(ours, exp.env.digest, "why", "x")
    with pytest.raises(RunDirError, match=r"record= needs the reason"):
        write_computed_physics(tmp_path, exp.env.digest, " ", "x")

    f = ours / "devices.yaml"                   # resumed onto other physics (allow_changes) than this checkout's
    f.write_text(yaml.safe_dump(yaml.safe_load(f.read_text()) + [{"model_digest": "0123456789abcdef"}]))
    capsys.readouterr()
    assert digest.main([f"runs=[{ours}]"]) == 1
    assert f"recorded {exp.env.digest} -> 0123456789abcdef; this checkout {exp.env.digest}: OTHER PHYSICS" in \
        capsys.readouterr().out
    (other / "physics.yaml").write_text("model_digest: 12\n")
    assert digest.main([f"runs=[{other}]"]) == 2             # a user's error: one line, no traceback
    assert "physics.yaml: expected a mapping with model_digest: 16 hex digits, found 12" in capsys.readouterr().err
    assert "physics.yaml: expected" in read_run(other).notes[-1]
    assert digest.main([f"runs=[{tmp_path / 'nothing'}]"]) == 2
