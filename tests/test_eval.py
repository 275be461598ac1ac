"""Evaluation sweeps on the shared smoke run: a batched sweep equals stepping each robot alone by hand; variants are
grouped by change type and counted; the files of `evaluate_run` agree with each other; the CLI reports bad input."""
from __future__ import annotations

import csv
import json
import os
import re
import shutil
import subprocess
import sys
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml

from mjx_morph.eval.evaluate import evaluate_run, resolve_set
from mjx_morph.eval.stats import TASK_RANGES, normalised
from mjx_morph.eval.sweep import Sweeper, episode_keys
from mjx_morph.layout import Obs
from mjx_morph.run import FAST_COMPILE, load_run, make_env_for
from mjx_morph.unimal.errors import RobotError
from mjx_morph.unimal.variants import CHANGE_TYPES, variant_change

ROOT = Path(__file__).resolve().parents[1]
from conftest import EVAL_STEPS as STEPS


@pytest.fixture(scope="module")
def loaded(smoke_run):
    run = load_run(smoke_run[0])
    cfg, env, model, ts = run.config, run.experiment.env, run.experiment.model, run.state
    short = make_env_for(cfg, env.morphologies, episode_length=STEPS)
    return cfg, short, model, ts


def test_sweep_equals_stepping_each_robot_alone(loaded):
    cfg, env, model, ts = loaded
    sweeper = Sweeper(env, model, trace_steps=STEPS, compiler_options=FAST_COMPILE)
    robots, episodes = np.array([1, 0, 1, 0]), np.array([0, 0, 1, 1])
    res = sweeper(ts.params, ts.obs_rms, robots, episodes, seed=3)
    assert res.reward.shape == (STEPS, 4)
    np.testing.assert_allclose(res.reward.sum(axis=0), res.ret, rtol=1e-5, atol=1e-5)
    assert not np.allclose(res.ret[0], res.ret[2])          # another episode key: another episode

    @partial(jax.jit, compiler_options=FAST_COMPILE)
    def act(state, carry, first):
        p = state.obs.proprio[None]
        obs = Obs(ts.obs_rms.normalize(p.reshape(1, -1)).reshape(p.shape), state.obs.prev_action[None],
                  state.obs.robot[None], state.obs.hfield[None])
        mu, _, carry = model.step(ts.params, env.robots, obs, carry, jnp.asarray([first]))
        return env.step(state, mu[0]), carry

    reset = jax.jit(env.reset, compiler_options=FAST_COMPILE)
    for i, (r, e) in enumerate(zip(robots, episodes)):
        key = episode_keys(3, env, jnp.asarray([r]), jnp.asarray([e]))[0]
        state, carry, ret, t = reset(key, jnp.int32(r)), model.initial_carry(1), 0.0, 0
        while True:
            state, carry = act(state, carry, t == 0)
            ret, t = ret + float(state.reward), t + 1
            if bool(state.done):
                break
        assert t == res.length[i], (i, t, res.length[i])
        np.testing.assert_allclose(ret, res.ret[i], rtol=1e-3, atol=1e-3)   # float32 physics, another program


def test_evaluate_run_groups_variants_and_writes_consistent_files(evaluated_runs):
    d = evaluated_runs[0]
    assert {p.name for p in (d / "eval").iterdir()} == {f"{t}.{x}" for t in ("train", "variants", "test")
                                                         for x in ("csv", "json")}
    # variants: 2 robots x 6 change types x 4, one sweep, summarised per change type
    v = json.loads((d / "eval" / "variants.json").read_text())
    assert v["robots"] == 48 and v["episodes_total"] == 96 and set(v["per_change"]) == set(CHANGE_TYPES)
    assert all(s["robots"] == 8 for s in v["per_change"].values())
    with (d / "eval" / "variants.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 96
    for c in CHANGE_TYPES:
        mine = [r for r in rows if r["change"] == c]
        assert len(mine) == 16 and all(r["robot"] == f"{r['base']}_{c}_{r['robot'][-1]}" for r in mine)
        # the CSV holds returns to 4 decimals (a mean near 0 makes a relative bound meaningless)
        np.testing.assert_allclose(np.mean([float(r["return"]) for r in mine]), v["per_change"][c]["mean_return"],
                                   rtol=1e-6, atol=1e-4)
        assert v["per_change"][c]["episodes_total"] == 16
        assert v["per_change"][c]["fall_fraction"] == pytest.approx(np.mean([int(r["fell"]) for r in mine]))
    assert {r["base"] for r in rows} == {m for m in json.loads((d / "eval" / "train.json").read_text())["per_robot"]}
    # the labelled set is the train robots again: same keys, same returns
    te = json.loads((d / "eval" / "test.json").read_text())
    assert te["tag"] == "test" and te["per_robot"] == json.loads((d / "eval" / "train.json").read_text())["per_robot"]
    # each file names the physics it simulated: the train robots' is the one the run trained on, the variants' another
    trained = yaml.safe_load((d / "devices.yaml").read_text())[-1]["model_digest"]
    assert te["model_digest"] == trained and v["model_digest"] != trained and len(v["model_digest"]) == 16
    # train: per-robot means, normalisation and the reward trace agree with the per-episode rows
    t = json.loads((d / "eval" / "train.json").read_text())
    with (d / "eval" / "train.csv").open() as fh:
        trows = list(csv.DictReader(fh))
    assert len(trows) == 4 and t["episodes"] == 2 and t["arch"] == "rmomo" and t["task"] == "ft"
    rets = np.array([float(r["return"]) for r in trows])
    np.testing.assert_allclose(np.array(t["reward_trace"]).sum() * 4, rets.sum(), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose([float(r["normalised"]) for r in trows], normalised(rets, "ft"), atol=1e-4)
    assert t["mean_normalised"] == pytest.approx((t["mean_return"] - TASK_RANGES["ft"][0]) / 4956, abs=1e-6)
    # the recurrent state held at zero for 10 steps changes the later rewards, not the first
    z = np.array(t["reward_trace_zero_state"])
    assert z[0] == pytest.approx(t["reward_trace"][0]) and not np.allclose(z[1:], t["reward_trace"][1:])


def test_evaluation_reports_progress_and_checks_its_input_first(evaluated_runs, tmp_path):
    from conftest import EVAL_LOG
    lines = [ln for ln in EVAL_LOG if "train:" in ln or ln.startswith("[mjx_morph] train (")]
    # rmomo on train: the env (its build time and self-collision pairs), the size (2 robots x 2 episodes, and the
    # zero-state sweep), then each chunk, then the result
    assert lines[0].startswith("[mjx_morph] train: building the env of 2 robots")
    assert lines[1].startswith("[mjx_morph] train: env built in ") and "self-collision pairs" in lines[1]
    assert re.search(r"\(tree [\d.]+ s, pairs [\d.]+ s, compile and put \(1 process\) [\d.]+ s, margins [\d.]+ s, "
                     r"stack [\d.]+ s, constants [\d.]+ s\)", lines[1]), lines[1]
    assert lines[2] == (f"[mjx_morph] train: 8 episodes x {STEPS} steps = {8 * STEPS} env steps in chunks of 4 "
                        "episodes; the first chunk includes compilation")
    assert "compilation included" in lines[3] and "compilation included" not in lines[4] and "left" in lines[4]
    assert lines[4].startswith(f"[mjx_morph]   train: {8 * STEPS:,}/{8 * STEPS:,} env steps")
    assert lines[5].startswith("[mjx_morph] train (gen/train, 2 robots x 2 episodes): mean return")
    d = tmp_path / "run"
    shutil.copytree(evaluated_runs[1], d)
    shutil.rmtree(d / "eval")
    for kw, msg in ((dict(episodes=0), "episodes=0: expected a positive number"),
                    (dict(sets=["no_such_set"]), "no_such_set")):
        with pytest.raises((ValueError, RobotError), match=msg):
            evaluate_run(d, **{"sets": ["train"], **kw})
        assert not (d / "eval").exists()


def test_zero_state_sweep_runs_on_the_test_set_alone_by_default(evaluated_runs, tmp_path):
    """The recurrent model's second sweep (state held at zero) is what the report reads from test.json only: by
    default train and val cost one sweep."""
    from conftest import EVAL_STEPS
    d = tmp_path / "run"
    shutil.copytree(evaluated_runs[0], d)
    shutil.rmtree(d / "eval")
    log = []
    evaluate_run(d, ["train", "test:train"], episodes=2, seed=0, zero_state_steps=10, episode_length=EVAL_STEPS,
                 trace_steps=EVAL_STEPS, log=log.append)
    train, test = (json.loads((d / "eval" / f"{t}.json").read_text()) for t in ("train", "test"))
    assert "reward_trace_zero_state" not in train and "mean_return_zero_state" not in train
    assert test["zero_state_steps"] == 10 and len(test["reward_trace_zero_state"]) == EVAL_STEPS
    assert any(ln.startswith("[mjx_morph] train: 4 episodes") for ln in log), log
    assert any(ln.startswith("[mjx_morph] test: 8 episodes") for ln in log), log


def test_another_run_of_the_same_model_reuses_the_compiled_sweep(evaluated_runs, tmp_path):
    """A second run of the same config (a study's other seed; here a copy of the metamorph run) builds no env and
    compiles nothing, and its results equal the first run's (same parameters)."""
    from conftest import EVAL_STEPS
    d = tmp_path / "run"
    shutil.copytree(evaluated_runs[1], d)
    shutil.rmtree(d / "eval")
    cfg = d / "config.yaml"                     # another training seed (the parameters stay the copied run's)
    assert "\nseed: 0\n" in cfg.read_text()
    cfg.write_text(cfg.read_text().replace("\nseed: 0\n", "\nseed: 7\n"))
    log = []
    out = evaluate_run(d, ["train"], episodes=2, seed=0, zero_state_steps=10, episode_length=EVAL_STEPS,
                       trace_steps=EVAL_STEPS, log=log.append)
    assert not any("building the env" in ln or "compilation" in ln for ln in log), log
    first = json.loads((evaluated_runs[1] / "eval" / "train.json").read_text())
    assert out["train"]["per_robot"] == first["per_robot"]
    # the summary names both seeds: the run's training seed and the evaluation episodes' seed
    saved = json.loads((d / "eval" / "train.json").read_text())
    assert (saved["train_seed"], saved["eval_seed"]) == (7, 0) and (first["train_seed"], first["eval_seed"]) == (0, 0)


def test_set_names_labels_and_keys_by_robot_name(loaded):
    cfg, env, model, ts = loaded
    es = resolve_set(cfg, "heldout:variants/gear")
    assert es.tag == "heldout" and es.name == "gen/train/variants/gear" and len(es.robots) == 8
    assert es.groups == {"gear": list(range(8))}
    assert {variant_change(m.name)[0] for m in es.robots} == {m.name for m in env.morphologies}
    with pytest.raises(ValueError, match="has no val set"):
        resolve_set(cfg, "val")
    # an episode's key depends on the robot's name, not on its index in the set
    swapped = make_env_for(cfg, env.morphologies[::-1], episode_length=STEPS)
    a = episode_keys(0, env, jnp.asarray([0, 1]), jnp.asarray([2, 2]))
    b = episode_keys(0, swapped, jnp.asarray([1, 0]), jnp.asarray([2, 2]))
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert not np.array_equal(np.asarray(a[0]), np.asarray(a[1]))


def test_evaluate_cli_reports_bad_input(tmp_path):
    env = {**os.environ, "HYDRA_FULL_ERROR": "0"}
    out = subprocess.run([sys.executable, "-m", "experiments.evaluate", f"run_dir={tmp_path}"], cwd=ROOT,
                         capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 2 and "not a run directory (no config.yaml)" in out.stderr


def test_context_feature_runs_see_only_their_feature():
    from conftest import smoke_config

    from mjx_morph.layout import CONTEXT_GROUPS, context_mask
    from mjx_morph.run import build
    env = build(smoke_config("env.context_features=[gear]")).env
    ctx = np.asarray(env.robots.context)
    keep = np.zeros(35, bool)
    keep[list(CONTEXT_GROUPS["gear"])] = True
    assert np.all(ctx[..., ~keep] == 0) and np.any(ctx[..., keep] != 0)
    assert sorted(i for c in CONTEXT_GROUPS.values() for i in c) == list(range(35))
    with pytest.raises(ValueError, match="unknown feature"):
        context_mask(["mass"])


def test_demo_trains_evaluates_and_reports(tmp_path, capsys):
    """`make demo`'s program end to end, on the smoke settings (whose compiled train step the smoke runs share); its
    video is left to tests/test_render.py, which records and renders an episode the same way."""
    from experiments import demo
    jax.clear_caches()      # lowered as in a fresh process, its train step is the smoke runs' (persistent cache)
    d = demo.demo(["preset=smoke", f"run_dir={tmp_path / 'demo'}", "progress=false"], unseen=2,
                  episode_length=STEPS, video=False)
    out = capsys.readouterr().out
    assert "[demo] cpu backend: the CPU demo" in out and "Outputs:" in out
    assert (d / "learning_curve.png").is_file() and (d / "report" / "report.md").is_file()
    test = json.loads((d / "eval" / "test.json").read_text())
    assert test["robots"] == 2 and test["set"] == "gen/test" and (d / "eval" / "train.json").is_file()
    assert "returns" in (d / "report" / "report.md").read_text().lower()
    assert "[demo] no video:" in out and not (d / "videos").exists()


def test_the_preparation_runs_below_the_trainings_priority(monkeypatch):
    """PrepareEvaluation's background thread lowers its own priority before it builds and compiles anything."""
    from mjx_morph.eval import evaluate as ev
    calls = []
    monkeypatch.setattr(ev, "lower_thread_priority", lambda: calls.append("lowered"))
    monkeypatch.setattr(ev, "prepare_evaluation",
                        lambda *a, on_start, on_set, **k: on_start("test") or calls.append("prepared")
                        or on_set("test", True))
    p = ev.PrepareEvaluation(lambda left_s: ["test"])
    p._prepare("cfg", "model", "like", ["test"], 4, log=print)
    assert calls == ["lowered", "prepared"] and p.prepared == ["test"] and p.preparing() == {}


def test_an_evaluation_prepared_while_training_builds_and_compiles_nothing_after(evaluated_runs, tmp_path,
                                                                                   monkeypatch):
    """prepare_evaluation (the study runs it in a background thread in training's last minutes) builds the env and
    compiles the sweep; the evaluate_run after it waits for it, then does neither, and its results equal those of an
    evaluation from scratch. evaluate_run itself prepares each next set while the sets before it sweep. On the rmomo
    smoke run and the demo's 2 unseen robots: the same sweep programs as evaluated_runs' train set and
    test_demo_trains_evaluates_and_reports' test set, which the persistent compilation cache then serves."""
    from collections import OrderedDict
    from mjx_morph.eval import evaluate as ev
    monkeypatch.setattr(ev, "_SWEEPERS", OrderedDict())          # nothing kept from the other tests
    d = tmp_path / "run"
    shutil.copytree(evaluated_runs[0], d)
    shutil.rmtree(d / "eval")
    run = load_run(d)
    kw = dict(episodes=2, episode_length=STEPS, trace_steps=STEPS)
    prep, log = [], []
    monkeypatch.setattr(ev, "_PREPARING", None)
    thread = ev.start_preparation(run.config, run.experiment.model, run.state, ["train"], 2, log=prep.append,
                                  target=partial(ev.prepare_evaluation, episode_length=STEPS, trace_steps=STEPS))
    out = evaluate_run(d, ["train"], seed=0, zero_state_steps=10, log=log.append, **kw)
    thread.join(60)
    assert not thread.is_alive() and not ev._is_pending("train")
    assert prep[0].startswith("[mjx_morph] train: building the env of 2 robots") and "env built in" in prep[1]
    assert prep[2].startswith("[mjx_morph] train: evaluation prepared while the run trained")
    assert "[mjx_morph] train: env and sweep prepared while the run trained" in log
    assert not any("building the env" in ln or "compilation" in ln for ln in log), log
    first = json.loads((evaluated_runs[0] / "eval" / "train.json").read_text())
    assert out["train"]["per_robot"] == first["per_robot"]

    # evaluate_run prepares the next set (its env build and compilation) while the sweeps of the one before run
    import dataclasses
    unseen = resolve_set(run.config, "test")
    unseen = dataclasses.replace(unseen, robots=unseen.robots[:2])      # the demo's (test_demo_trains_evaluates...)
    log.clear()
    out = evaluate_run(d, ["train", unseen], seed=0, zero_state_steps=0, log=log.append, **kw)
    assert out["train"]["per_robot"] == first["per_robot"] and out["test"]["robots"] == 2
    at = lambda text: next(i for i, ln in enumerate(log) if text in ln)
    assert at("test: building the env of 2 robots") < at("test: evaluation prepared while train's sweeps ran") \
        < at("test: env and sweep prepared while train's sweeps ran") < at("[mjx_morph] test (gen/test")
    assert not any("test:" in ln and "compilation included" in ln for ln in log), log


def test_an_evaluation_waits_for_its_own_sets_preparation_alone(monkeypatch):
    """start_preparation marks its sets pending before its thread starts; each set stops being pending as its
    preparation ends (on_start told as it starts, on_set as it ends), so the evaluation of test70 waits for test70's
    and not for the variants' still under way (session 28: 43-53 s). A failed preparation ends its sets too."""
    import threading
    from mjx_morph.eval import evaluate as ev
    release, order, told, log = threading.Event(), [], [], []

    def prepare_set(cfg, model, like, es, *args):
        if es.tag == "variants":
            release.wait(30)
        order.append(es.tag)
        return True
    monkeypatch.setattr(ev, "_prepare_set", prepare_set)
    monkeypatch.setattr(ev, "resolve_set", lambda cfg, name: ev.EvalSet(ev.set_tag(name), name, ()))
    monkeypatch.setattr(ev, "_PENDING", {})
    monkeypatch.setattr(ev, "_PREPARING", None)
    thread = ev.start_preparation("cfg", "model", "like", ["test", "variants"], log=log.append,
                                  target=partial(ev.prepare_evaluation, on_start=lambda n: told.append(n),
                                                 on_set=lambda n, ok: told.append((n, ok))))
    ev._await_pending("test", log.append)
    assert order == ["test"] and told[:2] == ["test", ("test", True)] and ev._is_pending("variants")
    ev._await_pending("train", log.append)                  # nothing prepared for it: no wait
    assert not any("train" in ln for ln in log)
    release.set()
    ev._await_pending("variants", log.append)
    assert order == ["test", "variants"] and not ev._is_pending("variants")
    assert told == ["test", ("test", True), "variants", ("variants", True)]     # each set started, then ended
    thread.join(30)
    assert not thread.is_alive() and ev._PENDING == {}
    monkeypatch.setattr(ev, "resolve_set", lambda cfg, name: 1 / 0)
    ev.start_preparation("cfg", "model", "like", ["test"], log=log.append).join(30)
    assert ev._PENDING == {} and "test: preparing the evaluation failed (ZeroDivisionError" in log[-1]
    monkeypatch.setattr(threading, "excepthook", lambda args: log.append(f"raised {args.exc_type.__name__}"))
    ev.start_preparation("cfg", "model", "like", ["test"], target=lambda *a, **k: 1 / 0).join(30)
    assert ev._PENDING == {} and log[-1] == "raised ZeroDivisionError"     # a target that raises ends them too


def test_prepare_evaluation_starts_once_when_little_training_is_left(monkeypatch):
    """The callback starts the preparation once: when iterations left x the median iteration time (the invocation's
    compiling first iteration left out) is within lead_s and the study names sets to prepare; with the train
    state's shapes, not its arrays (the next iteration donates them)."""
    from types import SimpleNamespace
    from mjx_morph.eval import evaluate as ev
    started, asked, preparing, between = [], [], [], []
    def prepare(cfg, model, like, names, episodes, log, on_start, on_set):
        started.append((cfg, model, like, names, episodes))
        for name in names:
            between.append(cb.preparing())
            on_start(name)
            preparing.append(cb.preparing())
            on_set(name, name != "test")
    monkeypatch.setattr(ev, "prepare_evaluation", prepare)
    monkeypatch.setattr(ev, "_PREPARING", None)
    monkeypatch.setattr(ev, "_PENDING", {})
    cb = ev.PrepareEvaluation(lambda s: asked.append(s) or (["test", "variants"] if s < 50 else []), episodes=3,
                              lead_s=100, log=lambda line: None)
    state = SimpleNamespace(params={"w": jnp.zeros((2, 3))}, obs_rms=jnp.ones(4, jnp.int32))
    loop = SimpleNamespace(start=10, stop=30, member=0, own=lambda s: s, config="cfg",
                           experiment=SimpleNamespace(model="model"))
    for it in range(11, 31):
        cb.on_iteration(loop, state, {"iteration": it, "wall_s": 90.0 if it == 11 else 10.0})
        if it == 25:
            assert ev._PREPARING is None
    ev.wait_for_preparation()
    assert ev._PREPARING is None and cb.prepared == ["variants"]
    # the set being prepared and the seconds its preparation has run, one set after the other; none once it ended
    assert [list(p) for p in preparing] == [["test"], ["variants"]] and cb.preparing() == {}
    assert between == [{}, {}]                  # none between one set's end and the next one's start
    assert all(0.0 <= s < 30.0 for p in preparing for s in p.values())
    assert asked == [100.0, 90.0, 80.0, 70.0, 60.0, 50.0, 40.0]              # iterations 20-26
    [(cfg, model, like, names, episodes)] = started
    assert (cfg, model, names, episodes) == ("cfg", "model", ["test", "variants"], 3)
    assert like.params["w"].shape == (2, 3) and isinstance(like.params["w"], jax.ShapeDtypeStruct)
    assert like.obs_rms.dtype == jnp.int32
