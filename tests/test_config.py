"""The run schema: one home per default, presets that only override, one-line errors for bad keys and values, and a
key followed from the command line to the object that uses it. Also: MJX's missing-Warp message is silenced."""
from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from mjx_morph import _WARP_MISSING
from mjx_morph.ppo.config import PPOConfig
from mjx_morph.run import ConfigError, RunConfig, compose_run_config, read_run_config, to_dict
from mjx_morph.run.config import CONF_DIR
from mjx_morph.sim.env import EnvConfig
from mjx_morph.sim.tasks import TASKS

ROOT = Path(__file__).resolve().parents[1]


def test_composed_default_is_the_schema_default():
    from mjx_morph.run.config import with_recommended
    cfg = compose_run_config([])
    assert cfg == with_recommended(dataclasses.replace(RunConfig(), compile_cache=cfg.compile_cache))
    assert cfg.ppo == PPOConfig() and cfg.env == EnvConfig()


@pytest.mark.parametrize("task", list(TASKS))
def test_env_group_picks_the_task(task):
    cfg = compose_run_config([f"env={task}", "env.self_collision=true"])
    assert cfg.env == EnvConfig(task=task, self_collision=True)


def _leaves(d, prefix=""):
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _leaves(v, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}", v


@pytest.mark.parametrize("preset", sorted(p.stem for p in (CONF_DIR / "preset").glob("*.yaml")))
def test_presets_only_override(preset):
    """A preset states no default again: every key it sets exists in the schema and differs from its default."""
    data = yaml.safe_load((CONF_DIR / "preset" / f"{preset}.yaml").read_text()) or {}
    defaults = dict(_leaves(to_dict(RunConfig())))
    for key, value in _leaves(data):
        assert key in defaults or key.startswith("model."), key
        assert defaults.get(key) != value, f"preset {preset} repeats the default of {key}"
    compose_run_config([f"preset={preset}"])


@pytest.mark.parametrize("override,words", [
    ("ppo.num_envs=abc", ["ppo.num_envs", "Integer"]),
    ("seed=abc", ["seed", "Integer"]),
    ("env.self_collision=maybe", ["env.self_collision", "bool"]),
    ("no_such_key=1", ["unknown config key", "no_such_key"]),
    ("model.dmodel=3", ["unknown config key", "model.dmodel"]),
    ("env=nope", ["env=nope", "ft, incline, csr, obstacle"]),
])
def test_bad_keys_and_values_give_one_line(override, words):
    with pytest.raises(ConfigError) as e:
        compose_run_config([override])
    msg = str(e.value)
    assert "\n" not in msg and all(w in msg for w in words), msg


def test_saved_config_is_read_back_and_a_foreign_one_is_refused(tmp_path):
    cfg = compose_run_config(["env=csr", "arch=modumorph", "model.d_model=64", "ppo.kl_threshold=0.03"])
    f = tmp_path / "config.yaml"
    f.write_text(yaml.safe_dump(to_dict(cfg)))
    assert read_run_config(f) == cfg
    f.write_text(yaml.safe_dump({**to_dict(cfg), "ppo": {"num_envs": "many"}}))
    with pytest.raises(ConfigError, match=r"config.yaml: ppo.num_envs: .*Integer"):
        read_run_config(f)


def test_a_key_reaches_its_use():
    """`ppo.kl_threshold`, `num_robots`, `model.d_model` and `env.episode_length` from the command line to the
    trainer, the env and the model that use them."""
    from mjx_morph.run import build
    exp = build(compose_run_config(["preset=smoke", "robots=gen/train", "ppo.kl_threshold=0.03", "model.d_model=8",
                                    "env.episode_length=77"]))
    assert exp.trainer.cfg.kl_threshold == 0.03 and exp.env.num_robots == 2
    assert exp.model.net.d_model == 8 and exp.env.config.episode_length == 77


def test_cli_reports_bad_values_on_one_line():
    out = subprocess.run([sys.executable, "-m", "experiments.run", "preset=smoke", "ppo.num_envs=abc"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and out.stderr.strip().splitlines() == [
        "error: ppo.num_envs=abc: Value 'abc' of type 'str' could not be converted to Integer"]


def test_missing_warp_message_is_silenced_but_other_output_is_not():
    out = subprocess.run([sys.executable, "-c", "import mjx_morph; from mujoco import mjx"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "warp" not in out.stdout + out.stderr
    assert _WARP_MISSING.fullmatch("Failed to import warp: No module named 'warp'")
    assert _WARP_MISSING.fullmatch("Failed to import mujoco_warp: No module named 'warp'")
    assert not _WARP_MISSING.fullmatch("Failed to import warp: CUDA driver version is insufficient")


def test_study_plan_passes_env_options_and_extra_overrides(capsys):
    from experiments import study
    assert study.main(["train_size", "archs=[metamorph]", "seeds=[1]", "env=incline", "env.self_collision=false",
                       "dry_run=true", "--", "preset=smoke", "total_steps=512"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 4 and all("env=incline env.self_collision=False arch=metamorph seed=1" in ln
                                   and ln.endswith("preset=smoke total_steps=512   # then evaluate ['train', 'test']")
                                   for ln in lines)
    assert study.main(["no_such_study"]) == 2 and "no study 'no_such_study'" in capsys.readouterr().err


def test_a_study_named_with_its_task_is_that_study_on_that_task(capsys):
    """`<study>_<task>` (issue 15's `paper_ft`) plans what `<study> env=<task>` plans, in the same run directories;
    another env= beside it is refused, and a name whose tail is no task is still an unknown study."""
    from experiments import study
    plans = {}
    for args in (["train_size_incline"], ["train_size", "env=incline"], ["train_size_incline", "env=incline"]):
        assert study.main([*args, "archs=[metamorph]", "seeds=[1]", "dry_run=true"]) == 0
        plans[tuple(args)] = capsys.readouterr().out
    assert len(set(plans.values())) == 1
    lines = plans[("train_size_incline",)].strip().splitlines()
    assert len(lines) == 4 and all(ln.startswith("python -m experiments.run env=incline arch=metamorph seed=1 "
                                                 "run_dir=runs/studies/train_size/incline-metamorph-") for ln in lines)
    assert study.main(["train_size_incline", "env=ft", "dry_run=true"]) == 2
    err = capsys.readouterr().err
    assert "train_size_incline is the study train_size on incline, but env=ft was given too" in err
    assert study.main(["train_size_walking", "dry_run=true"]) == 2
    assert "no study 'train_size_walking'" in capsys.readouterr().err


@pytest.mark.parametrize("name,archs,runs", [("ab_rmomo_cell", {"rmomo"}, 2), ("ab_rmomo_residual", {"rmomo"}, 2),
                                             ("ab_rmemo_context", {"rmemo"}, 3),
                                             ("ab_geometry", {"rmomo", "modumorph"}, 3),
                                             ("ab_precision", {"rmomo", "modumorph"}, 3),
                                             ("kl_threshold", {"metamorph", "modumorph", "rmemo", "rmomo"}, 2)])
def test_ab_studies_compose(capsys, unimals, name, archs, runs):
    """The issue-15 studies: their own architectures, the 100 M schedule for every run (the A/Bs: its first 20 M steps;
    the KL-threshold choice: all of it), and every run's config and evaluation sets valid (the study checks them all
    before printing; the val set needs the original robots)."""
    from experiments import study
    assert study.main([name, "seeds=[0,1]", "dry_run=true"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 2 * len(archs) * runs
    assert {ln.split("arch=")[1].split()[0] for ln in lines} == archs
    assert all("total_steps=100000000" in ln for ln in lines)
    assert all("stop_at=245" in ln for ln in lines) == (name != "kl_threshold")


def test_the_solver_study_differs_from_the_paper_runs_in_the_solver_cap_alone(capsys, unimals):
    """ab_solver (plan item 2): its two arms are the paper study's runs (100 M schedule stopped at 220, as its seeds
    7-8) with the Newton solver capped at 5 (the comparison's seeds) or converged at 16, and nothing else."""
    from experiments import study
    assert study.main(["ab_solver", "env=ft", "dry_run=true"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 8 and {ln.split("arch=")[1].split()[0] for ln in lines} == {"metamorph", "rmemo"}
    for ln in lines:
        cmd = ln.split("   #")[0].split()
        arm = "converged" if "-converged-" in ln else "capped"
        assert cmd[-3:] == ["total_steps=100000000", "stop_at=220",
                            f"env.iterations={16 if arm == 'converged' else 5}"], ln
        assert ln.endswith("# then evaluate ['test', 'variants']") and ("seed=7" in cmd or "seed=8" in cmd)

def test_study_workers_split_the_runs_one_gpu_each(capsys, monkeypatch, unimals):
    """workers=N: every run of the plan goes to exactly one worker, the seeds of a run to different workers; each
    worker is the same study with worker=k on GPU k alone, its lines relayed with [w<k>]; a failed worker fails the
    study, naming it. Without workers=, one worker per visible GPU (at most one per run)."""
    from experiments import study
    assert study.main(["ab_precision", "seeds=[0,1]", "workers=2", "dry_run=true"]) == 0
    shares = [ln.split(": ")[1].split(", ") for ln in capsys.readouterr().out.splitlines()
              if ln.startswith("[study] worker")]
    assert len(shares) == 2 and sorted(shares[0] + shares[1]) == sorted(
        f"ft-{a}-{r}-s{s}" for a in ("rmomo", "modumorph") for r in ("fp32", "tf32", "bf16") for s in (0, 1))
    assert all(d.endswith(f"-s{k}") for k in (0, 1) for d in shares[k])
    assert study.main(["ab_precision", "seeds=[0,1]", "workers=2", "worker=1", "dry_run=true"]) == 0
    mine = capsys.readouterr().out.strip().splitlines()       # a worker lists its own share
    assert len(mine) == 6 and all("seed=1" in ln for ln in mine)
    assert study.main(["ab_precision", "workers=2", "worker=2"]) == 2
    assert "worker in 0..workers-1" in capsys.readouterr().err

    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "4,7")
    fake = ("import os, sys; g = os.environ['CUDA_VISIBLE_DEVICES']; print('gpu', g, sys.argv[-1]); "
            "sys.exit(3 if g == '7' else 0)")
    monkeypatch.setattr(study, "worker_command",
                        lambda argv, n, k: [sys.executable, "-c", fake, *argv, f"workers={n}", f"worker={k}"])
    assert study.main(["ab_precision", "only=[fp32]", "archs=[rmomo]", "seeds=[0,1]", "workers=2"]) == 2
    cap = capsys.readouterr()
    assert "[w0] gpu 4 worker=0" in cap.out and "[w1] gpu 7 worker=1" in cap.out
    assert "worker 1 (exit status 3) failed" in cap.err and "worker 0" not in cap.err
    # no workers=: one per visible GPU, at most one per run
    assert study.main(["ab_precision", "seeds=[0,1]", "dry_run=true"]) == 0
    assert sum(ln.startswith("[study] worker") for ln in capsys.readouterr().out.splitlines()) == 2
    assert study.main(["ab_precision", "only=[fp32]", "archs=[rmomo]", "seeds=[0]", "dry_run=true"]) == 0
    assert "[study] worker" not in capsys.readouterr().out
    assert study.worker_command(["ab_precision", "workers=5", "seeds=[0]"], 2, 1)[-3:] == \
        ["seeds=[0]", "workers=2", "worker=1"]
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "0")
    assert study.main(["ab_precision", "only=[fp32]", "archs=[rmomo]", "seeds=[0,1]", "workers=2"]) == 2
    assert "only 1 GPU(s) visible (CUDA_VISIBLE_DEVICES=0)" in capsys.readouterr().err


def run_dirs_at(steps: dict):
    """A stand-in for experiments.study's RunDir: each run directory's latest checkpoint read from `steps` by the
    directory's name (None where it has none)."""
    class At:
        def __init__(self, d):
            self.name = Path(d).name

        def latest_step(self):
            return steps.get(self.name)
    return At


def test_study_neither_trains_nor_evaluates_a_run_that_starts_broken(capsys, monkeypatch, tmp_path, unimals):
    """A run the loop stopped because it starts broken (its unhealthy.txt, `stop_unhealthy`) is named, not trained
    further and not evaluated; the study goes on with the rest (here its healthy seed, trained alone and side by
    side), on this invocation and the next; `-- stop_unhealthy=false` trains it on."""
    from experiments import study
    from mjx_morph.run import UNHEALTHY
    steps, calls = {}, []

    def fake_train(cfg, callbacks=None):
        seeds = cfg.seeds if cfg.seeds is not None else [cfg.seed]
        calls.append(("train", seeds, cfg.stop_unhealthy))
        for seed in seeds:
            d = Path(cfg.run_dir.replace("{seed}", str(seed)))
            d.mkdir(parents=True, exist_ok=True)
            if seed == 0 and cfg.stop_unhealthy:
                (d / UNHEALTHY).write_text("iteration 1's value estimates average 4.6e+05, where ...\n")
                steps[d.name] = 1
            else:
                steps[d.name] = 245
    monkeypatch.setattr(study, "RunDir", run_dirs_at(steps))
    monkeypatch.setattr(study, "train", fake_train)
    monkeypatch.setattr(study, "evaluated", lambda d, s, step, episodes: False)
    monkeypatch.setattr(study, "evaluate_run", lambda d, sets, episodes: calls.append(("eval", Path(d).name)))
    monkeypatch.setattr(study, "use_compile_cache", lambda path: None)
    for side in ("true", "false"):
        steps.clear(), calls.clear()
        out_dir = tmp_path / side
        args = ["ab_rmemo_context", "only=[no_context]", "seeds=[0,1]", f"out={out_dir}", "prepare_eval=false",
                f"side_by_side={side}"]
        assert study.main(args) == 0
        trained = [("train", [0, 1], True)] if side == "true" else [("train", [0], True), ("train", [1], True)]
        assert calls == [*trained, ("eval", "ft-rmemo-no_context-s1")], side
        out = capsys.readouterr().out
        assert out.count("ft-rmemo-no_context-s0: stopped, it starts broken (iteration 1's value") == 1
        calls.clear()
        assert study.main(args) == 0                        # the next call: nothing trained, s0 named again
        assert calls == [("eval", "ft-rmemo-no_context-s1")]
        assert "ft-rmemo-no_context-s0: stopped, it starts broken" in capsys.readouterr().out
    calls.clear()
    assert study.main([*args, "--", "stop_unhealthy=false"]) == 0
    assert calls == [("train", [0], False), ("eval", "ft-rmemo-no_context-s0"), ("eval", "ft-rmemo-no_context-s1")]


def test_study_time_limit_evaluates_what_fits(capsys, monkeypatch, tmp_path, unimals):
    """With time_limit_min, a finished batch gets as many (set, run) evaluations as fit (eval_minutes each), the study
    file's sets in order over the seeds, one evaluate_run per run; the rest are named and left for the rerun; with
    no time left none runs."""
    from types import SimpleNamespace
    from experiments import study

    class Finished:                             # every run at its last checkpoint: nothing to train
        def __init__(self, d):
            pass

        def latest_step(self):
            return 245
    calls = []
    monkeypatch.setattr(study, "RunDir", Finished)
    monkeypatch.setattr(study, "train", lambda cfg: pytest.fail("a finished run was trained"))
    monkeypatch.setattr(study, "evaluated", lambda d, s, step, episodes: False)
    monkeypatch.setattr(study, "evaluate_run", lambda d, sets, episodes: calls.append((Path(d).name, list(sets))))
    monkeypatch.setattr(study, "use_compile_cache", lambda path: None)
    monkeypatch.setattr(study, "time", SimpleNamespace(monotonic=lambda: 0.0))   # minutes left = the limit
    args = ["ab_rmemo_context", "only=[no_context]", "seeds=[0,1]", f"out={tmp_path}"]
    val, train = study.eval_minutes("val"), study.eval_minutes("train")
    assert study.main([*args, f"time_limit_min={2 * val + 0.9 * train}"]) == 0       # 2 of 4 fit: val, both seeds
    assert calls == [("ft-rmemo-no_context-s0", ["val"]), ("ft-rmemo-no_context-s1", ["val"])]
    out = capsys.readouterr().out
    assert "ft-rmemo-no_context-s0: train" in out and "left for the rerun" in out and "[study] done" not in out
    calls.clear()
    assert study.main([*args, f"time_limit_min={0.9 * val}"]) == 0
    assert calls == [] and "left for the rerun" in capsys.readouterr().out
    assert study.main([*args, "time_limit_min=100"]) == 0
    assert calls == [("ft-rmemo-no_context-s0", ["val", "train"]), ("ft-rmemo-no_context-s1", ["val", "train"])]
    assert "[study] done" in capsys.readouterr().out
    # sets already evaluated take none of the time: with val done for both seeds, one slot goes to s0's train
    calls.clear()
    monkeypatch.setattr(study, "evaluated", lambda d, s, step, episodes: s == "val")
    assert study.main([*args, f"time_limit_min={1.9 * train}"]) == 0
    assert calls == [("ft-rmemo-no_context-s0", ["train"])]
    out = capsys.readouterr().out
    assert "ft-rmemo-no_context-s1: val already evaluated at checkpoint 245" in out
    assert "ft-rmemo-no_context-s1: train left for the rerun" in out
    # each set its own time: the variants take longer than test70, so time for the variants and part of test70
    # evaluates the variants alone, and an unknown set gets the largest of the small sets' time
    calls.clear()
    monkeypatch.setattr(study, "evaluated", lambda d, s, step, episodes: False)
    limit = study.eval_minutes("variants") + 0.9 * study.eval_minutes("test")
    assert 2 * study.eval_minutes("train") <= limit and study.eval_minutes("unimal100/test") == study.EVAL_SET_MIN
    assert study.eval_minutes("test") < study.eval_minutes("val") < study.eval_minutes("train")
    assert study.main(["paper", "archs=[rmomo]", "seeds=[0]", "evaluate=[variants,test]", f"out={tmp_path}",
                       f"time_limit_min={limit}", "--", "stop_at=245"]) == 0
    assert calls == [("ft-rmomo-main-s0", ["variants"])]
    assert "ft-rmomo-main-s0: test left for the rerun" in capsys.readouterr().out
    # a set too long for the time left gives way to a shorter one after it: the variants do not fit, test70 does
    calls.clear()
    limit = study.eval_minutes("test") + 0.1
    assert study.eval_minutes("variants") > limit
    assert study.main(["paper", "archs=[rmomo]", "seeds=[0]", "evaluate=[variants,test]", f"out={tmp_path}",
                       f"time_limit_min={limit}", "--", "stop_at=245"]) == 0
    assert calls == [("ft-rmomo-main-s0", ["test"])]
    assert "ft-rmomo-main-s0: variants left for the rerun" in capsys.readouterr().out


def test_study_starts_the_next_run_only_once_the_last_ones_evaluations_are_done(capsys, monkeypatch, tmp_path,
                                                                                 unimals):
    """A lease's last call names the run it finishes before the one it starts ('archs=[rmomo,modumorph]', docs/
    leases.md's plan): the study evaluates what the finished run still lacks, and trains the next run only once
    those evaluations are all done, so that no decision falls between a lease's calls."""
    from types import SimpleNamespace
    from experiments import study
    trained, calls = [], []
    monkeypatch.setattr(study, "RunDir", run_dirs_at({"ft-rmomo-main-s0": 245, "ft-modumorph-main-s0": 0}))
    monkeypatch.setattr(study, "train", lambda cfg, callbacks=None: trained.append(Path(cfg.run_dir).name))
    monkeypatch.setattr(study, "evaluated", lambda d, s, step, episodes: s != "variants")
    monkeypatch.setattr(study, "evaluate_run", lambda d, sets, episodes: calls.append((Path(d).name, list(sets))))
    monkeypatch.setattr(study, "use_compile_cache", lambda path: None)
    monkeypatch.setattr(study, "time", SimpleNamespace(monotonic=lambda: 0.0))
    args = ["paper", "archs=[rmomo,modumorph]", "seeds=[0]", "evaluate=[test,variants]", f"out={tmp_path}",
            "prepare_eval=false"]
    short = 0.9 * study.eval_minutes("variants")            # the variants left: ModuMorph's run is not started
    assert study.main([*args, f"time_limit_min={short}", "--", "stop_at=245"]) == 0
    assert calls == [] and trained == []
    assert "evaluation of " in (out := capsys.readouterr().out) and "ft-rmomo-main-s0 left for the rerun" in out
    assert study.main([*args, "time_limit_min=100", "--", "stop_at=245"]) == 0
    assert calls == [("ft-rmomo-main-s0", ["variants"])] and trained == ["ft-modumorph-main-s0"]


def test_study_prepares_the_evaluations_its_time_limit_will_run(capsys, monkeypatch, tmp_path, unimals):
    """The study trains with the default callbacks and PrepareEvaluation, which prepares the sets that the time
    left after the training will let it evaluate (the same count as after the training); prepare_eval=false: the
    default callbacks alone."""
    from types import SimpleNamespace
    from experiments import study
    from mjx_morph.eval.evaluate import PrepareEvaluation
    from mjx_morph.run import MetricsLog

    class Untrained:
        def __init__(self, d):
            pass

        def latest_step(self):
            return None
    given = []
    monkeypatch.setattr(study, "RunDir", Untrained)
    monkeypatch.setattr(study, "train", lambda cfg, callbacks=None: given.append(callbacks))
    monkeypatch.setattr(study, "use_compile_cache", lambda path: None)
    monkeypatch.setattr(study, "time", SimpleNamespace(monotonic=lambda: 0.0))   # minutes left = the limit
    args = ["paper", "archs=[rmomo]", "seeds=[0]", "evaluate=[val,test]", f"out={tmp_path}", "time_limit_min=10",
            "--", "stop_at=245"]
    assert study.main(args) == 0 and "rerun the same command to go on" in capsys.readouterr().out
    [callbacks] = given
    assert isinstance(callbacks[0], MetricsLog) and isinstance(callbacks[-1], PrepareEvaluation)
    val, test = study.eval_minutes("val", prepared=True), study.eval_minutes("test", prepared=True)
    assert val < study.eval_minutes("val") and test < study.eval_minutes("test")
    assert study.eval_minutes("variants", prepared=True) < study.eval_minutes("variants")
    sets = callbacks[-1].sets
    assert sets(60.0 * (10 - val - test)) == ["val", "test"]
    assert sets(60.0 * (10 - val - 0.5 * test)) == ["val"]
    assert sets(60.0 * (10 - 0.9 * val)) == []
    assert study.main([*args[:-2], "prepare_eval=false", *args[-2:]]) == 0
    assert given[-1] is None
    # after the training, the sets prepared cost their prepared time: with half a minute more than that left both
    # fit, without preparation val alone
    trained, calls = set(), []

    class Trained(Untrained):
        def __init__(self, d):
            self.d = d

        def latest_step(self):
            return 245 if self.d in trained else None

    def train(cfg, callbacks=None):
        trained.add(tmp_path / "paper" / "ft-rmomo-main-s0")
        if callbacks:
            callbacks[-1].prepared = ["val", "test"]
    monkeypatch.setattr(study, "RunDir", Trained)
    monkeypatch.setattr(study, "train", train)
    monkeypatch.setattr(study, "evaluated", lambda d, s, step, episodes: False)
    monkeypatch.setattr(study, "evaluate_run", lambda d, sets, episodes: calls.append(list(sets)))
    limit = study.eval_minutes("val", True) + study.eval_minutes("test", True) + 0.5
    assert limit < study.eval_minutes("val") + study.eval_minutes("test")
    short = [*args[:5], f"time_limit_min={limit}", *args[-2:]]
    assert study.main(short) == 0 and calls == [["val", "test"]]
    trained.clear()
    assert study.main([*short[:-2], "prepare_eval=false", *short[-2:]]) == 0 and calls[-1] == ["val"]
    # a set still being prepared counts at its unprepared time less what its preparation has run, down to its
    # prepared time (session 30: the variants, seconds from prepared, counted at 5.5 minutes and were left out)
    full, ready = study.eval_minutes("variants"), study.eval_minutes("variants", prepared=True)
    assert study.eval_minutes("variants", preparing_s=30.0) == pytest.approx(full - 0.5)
    assert study.eval_minutes("variants", preparing_s=1e4) == ready
    preparing = {"variants": 60.0 * (full - ready)}

    def train_preparing(cfg, callbacks=None):
        trained.add(tmp_path / "paper" / "ft-rmomo-main-s0")
        callbacks[-1].prepared = ["test"]
        callbacks[-1].preparing = lambda: preparing
    monkeypatch.setattr(study, "train", train_preparing)
    limit = study.eval_minutes("test", True) + ready + 0.3
    assert limit < study.eval_minutes("test", True) + full
    args = [*args[:3], "evaluate=[test,variants]", *args[4:5], f"time_limit_min={limit}", *args[-2:]]
    trained.clear()
    assert study.main(args) == 0 and calls[-1] == ["test", "variants"]
    preparing = {}                      # not started: its whole unprepared time, and it gives way
    trained.clear()
    assert study.main(args) == 0 and calls[-1] == ["test"]
    assert "ft-rmomo-main-s0: variants left for the rerun" in capsys.readouterr().out


def test_study_only_selects_runs_and_names_the_known_ones(capsys, unimals):
    from experiments import study
    assert study.main(["ab_rmomo_residual", "only=[residual,replace]", "seeds=[3]", "dry_run=true"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert [ln.split("run_dir=")[1].split()[0].rsplit("/", 1)[1] for ln in lines] == \
        ["ft-rmomo-replace-s3", "ft-rmomo-residual-s3"]
    assert study.main(["ab_rmomo_cell", "only=[scale_afte]", "dry_run=true"]) == 2
    err = capsys.readouterr().err
    assert "only=['scale_afte']" in err and "scale_before, scale_after" in err
    # evaluation sets are checked before anything trains: gen/train has no val set
    assert study.main(["ab_rmomo_cell", "only=[scale_before]", "--", "robots=gen/train"]) == 2
    assert "no val set" in capsys.readouterr().err


def test_study_seeds_of_gives_an_architecture_other_seeds(capsys, unimals):
    """seeds_of.<arch>=[...]: that architecture's seeds replace seeds= for it alone (one lease's plan of the runs each
    model still needs, split over the workers one run each); an architecture outside the plan is refused."""
    from experiments import study
    assert study.main(["paper", "archs=[rmomo,metamorph]", "seeds=[2]", "seeds_of.rmomo=[6,7]", "workers=3",
                       "dry_run=true"]) == 0
    out = capsys.readouterr().out
    runs = [ln for ln in out.splitlines() if ln.startswith("python -m experiments.run")]
    assert [(ln.split("arch=")[1].split()[0], ln.split("seed=")[1].split()[0]) for ln in runs] == \
        [("rmomo", "6"), ("rmomo", "7"), ("metamorph", "2")]
    assert sorted(ln.split(": ")[1] for ln in out.splitlines() if ln.startswith("[study] worker")) == \
        ["ft-metamorph-main-s2", "ft-rmomo-main-s6", "ft-rmomo-main-s7"]
    assert study.main(["paper", "archs=[rmomo]", "seeds_of.modumorph=[1]", "dry_run=true"]) == 2
    assert "modumorph not among the study's architectures (rmomo)" in capsys.readouterr().err


def test_study_stop_at_of_gives_an_architecture_its_own_stop(capsys, unimals):
    """stop_at_of.<arch>=N: that architecture's runs stop at N, over the stop_at given to every run after --, the
    others keep it (one lease: R-MoMo to 20.1 M steps as its earlier seeds, MetaMorph to 18.0 M as its own)."""
    from experiments import study
    assert study.main(["paper", "archs=[rmomo,metamorph]", "seeds=[4]", "stop_at_of.rmomo=245", "dry_run=true",
                       "--", "progress=false", "stop_at=220"]) == 0
    runs = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("python -m experiments.run")]
    stops = {ln.split("arch=")[1].split()[0]: [o for o in ln.split() if o.startswith("stop_at=")] for ln in runs}
    assert stops == {"rmomo": ["stop_at=245"], "metamorph": ["stop_at=220"]}
    assert all("progress=false" in ln for ln in runs)
    assert study.main(["paper", "archs=[rmomo]", "stop_at_of.metamorph=220", "dry_run=true"]) == 2
    assert "stop_at_of={'metamorph': 220}: metamorph not among" in capsys.readouterr().err


def test_study_evaluate_overrides_the_study_files_sets(capsys, unimals):
    """evaluate=[...] replaces the study file's sets and their order (the zero-shot sets first under a time limit);
    a set the run's robots have not is refused before anything trains."""
    from experiments import study
    assert study.main(["paper", "archs=[rmomo]", "seeds=[0]", "dry_run=true"]) == 0
    assert "then evaluate ['test', 'variants', 'val', 'train']" in capsys.readouterr().out
    assert study.main(["paper", "archs=[rmomo]", "seeds=[0]", "evaluate=[test,variants]", "dry_run=true"]) == 0
    assert "then evaluate ['test', 'variants']" in capsys.readouterr().out
    assert study.main(["paper", "archs=[rmomo]", "seeds=[0]", "evaluate=[val]", "--", "robots=gen/train"]) == 2
    assert "no val set" in capsys.readouterr().err


def test_last_iteration_and_evaluated(tmp_path):
    """What the study's time limit relies on: where a run ends (schedule or stop_at) and whether a set was evaluated
    at a checkpoint with the same number of episodes."""
    import json
    from mjx_morph.eval.evaluate import evaluated, set_tag
    cfg = compose_run_config(["total_steps=100000000"])
    assert cfg.last_iteration() == 100_000_000 // 81_920 == 1220
    assert compose_run_config(["total_steps=100000000", "stop_at=245"]).last_iteration() == 245
    assert compose_run_config(["total_steps=1000"]).last_iteration() == 1         # at least one iteration
    assert set_tag("unimal100/test70") == "unimal100_test70" and set_tag("t70:unimal100/test70") == "t70"
    (tmp_path / "eval").mkdir()
    (tmp_path / "eval" / "val.json").write_text(json.dumps({"checkpoint": 245, "episodes": 4}))
    assert evaluated(tmp_path, "val", 245, 4)
    assert not evaluated(tmp_path, "val", 240, 4) and not evaluated(tmp_path, "val", 245, 8)
    assert not evaluated(tmp_path, "train", 245, 4)
    (tmp_path / "eval" / "train.json").write_text("{trunc")
    assert not evaluated(tmp_path, "train", 245, 4)


def test_recommended_model_options_are_filled_and_recorded(tmp_path):
    """R-MoMo's and R-MeMo's measured scale_after_cell=True (and R-MeMo's context_mlp=True, scale_context=True) is
    filled in at composition (recorded explicitly in config.yaml) unless the run names the key, or, for scale_context,
    the context MLP is off; a run directory saved with null (the spec's reading) or without the key refuses the new
    default with a hint, and resumes with model.<key>=null."""
    from mjx_morph.run import RunDir, RunDirError
    from mjx_morph.run.config import FREE, IDENTITY
    assert compose_run_config(["arch=rmomo"]).model.scale_after_cell is True
    assert compose_run_config(["arch=grumomo"]).model.scale_after_cell is True
    assert compose_run_config(["arch=rmomo", "model.scale_after_cell=false"]).model.scale_after_cell is False
    assert compose_run_config(["arch=rmomo", "model.scale_after_cell=null"]).model.scale_after_cell is None
    assert compose_run_config(["arch=modumorph"]).model.scale_after_cell is None      # not an option of modumorph
    assert compose_run_config(["arch=rmemo"]).model.context_mlp is True                # R-MeMo's measured context MLP
    assert compose_run_config(["arch=rmemo", "model.context_mlp=false"]).model.context_mlp is False
    assert compose_run_config(["arch=rmemo"]).model.scale_after_cell is True          # R-MeMo's measured scale
    assert compose_run_config(["arch=metamorph"]).model.scale_after_cell is None      # no cell: not an option
    assert to_dict(compose_run_config(["arch=rmomo"]))["model"]["scale_after_cell"] is True
    old = compose_run_config(["arch=rmomo", "model.scale_after_cell=null", f"run_dir={tmp_path}"])
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(to_dict(old), sort_keys=False))
    new = compose_run_config(["arch=rmomo", f"run_dir={tmp_path}"])
    with pytest.raises(RunDirError, match=r"model.scale_after_cell: saved None, now True \(saved null: pass "
                                          r"model.scale_after_cell=null"):
        RunDir(tmp_path, to_dict(new), IDENTITY, FREE)
    RunDir(tmp_path, to_dict(old), IDENTITY, FREE)          # the same null: resumes
    # R-MeMo's measured scale_context=True; not where its prerequisite, the context MLP, is off (design A)
    assert compose_run_config(["arch=rmemo"]).model.scale_context is True
    design_a = compose_run_config(["arch=rmemo", "model.context_mlp=false"])
    assert design_a.model.scale_context is None and design_a.model.scale_after_cell is True
    assert compose_run_config(["arch=rmemo", "model.scale_context=false"]).model.scale_context is False
    # a run directory from before the key (config.yaml without it) gets the same hint
    saved = to_dict(compose_run_config(["arch=rmemo", "model.scale_context=null", f"run_dir={tmp_path}"]))
    del saved["model"]["scale_context"]
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(saved, sort_keys=False))
    with pytest.raises(RunDirError, match=r"model.scale_context: saved None, now True \(saved without the key: pass "
                                          r"model.scale_context=null"):
        RunDir(tmp_path, to_dict(compose_run_config(["arch=rmemo", f"run_dir={tmp_path}"])), IDENTITY, FREE)
    RunDir(tmp_path, to_dict(compose_run_config(["arch=rmemo", "model.scale_context=null", f"run_dir={tmp_path}"])),
           IDENTITY, FREE)


def test_paper_study_runs_the_four_models_with_three_seeds(capsys, unimals):
    """`experiments.study paper env=<task>`: the study file's seeds and archs are the defaults, every run on the
    100 M schedule, evaluated on train, val, test and the variants."""
    from experiments import study
    assert study.main(["paper", "env=incline", "dry_run=true"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert sorted((ln.split("arch=")[1].split()[0], ln.split("seed=")[1].split()[0]) for ln in lines) == \
        sorted((a, str(s)) for a in ("metamorph", "modumorph", "rmemo", "rmomo") for s in (0, 1, 2))
    assert all(ln.startswith("python -m experiments.run env=incline") and "total_steps=100000000" in ln
               and ln.endswith("['test', 'variants', 'val', 'train']") for ln in lines)
    assert study.main(["paper", "seeds=[5]", "dry_run=true"]) == 0
    assert len(capsys.readouterr().out.strip().splitlines()) == 4


def test_every_study_files_runs_compose_and_build_their_models():
    """Every run of every study file (each architecture, its seed 0) composes into a run config whose model options
    `make_model` accepts: a study that names an option its architecture lacks fails here, not on a GPU machine."""
    from experiments import study
    from mjx_morph.run.build import make_model_for
    files = sorted((CONF_DIR / "study").glob("*.yaml"))
    assert {"paper", "ab_rmemo_context_path"} <= {f.stem for f in files}
    seen = set()
    for f in files:
        runs = study.plan(study.StudyConfig(name=f.stem, seeds=[0]))
        assert runs, f
        for r in runs:
            over = tuple(o for o in r.overrides if not o.startswith(("run_dir=", "seed=")))
            if over in seen:
                continue
            seen.add(over)
            model = make_model_for(compose_run_config(list(over)))
            assert model.arch == r.group[0], (f.stem, r.group)


def test_the_suite_compiles_every_program_with_fast_compiles_options():
    """tests/conftest.py sets FAST_COMPILE's options in XLA_FLAGS before JAX starts (it cannot import them from
    mjx_morph, which imports JAX): the two lists must stay one."""
    import os
    from conftest import CPU_FLAGS
    from mjx_morph.run import FAST_COMPILE
    assert sorted(CPU_FLAGS) == sorted(f"--{k}={str(v).lower()}" for k, v in FAST_COMPILE.items())
    assert all(f in os.environ["XLA_FLAGS"].split() for f in CPU_FLAGS)
