"""The main job in miniature: `make demo` (`python -m experiments.demo`).

Trains R-MoMo on shipped generated robots, evaluates it zero-shot on generated robots it has never seen, and writes
a report (learning curve, zero-shot returns) and, where OpenGL exists, a video. On a CPU it runs `preset=demo`
(4 robots, a small network, 81,920 env steps: about 5 minutes of training on 2 cores); with an accelerator it runs the
full-size R-MoMo on all 100 gen/train robots for 2 M steps. Extra `key=value` arguments override the training config.
"""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import jax

from mjx_morph.eval.evaluate import evaluate_run, resolve_set
from mjx_morph.eval.report import build_report
from mjx_morph.eval.video import EpisodeRecorder, episode_frames, render_video
from mjx_morph.run import FAST_COMPILE, compose_run_config, load_run, make_env_for, train
from mjx_morph.unimal import render

from . import cli

CPU = ["preset=demo", "robots=gen/train", "run_dir=runs/demo"]
ACCELERATOR = ["env=ft", "arch=rmomo", "robots=gen/train", "total_steps=2000000", "run_dir=runs/demo-gpu"]
UNSEEN_CPU = 8          # unseen robots evaluated on a CPU (all 100 of gen/test with an accelerator)


def demo(extra: list[str], unseen: int | None = None, episode_length: int | None = None, video: bool = True) -> Path:
    """Train, evaluate, report; returns the run directory. `extra`: overrides of the training config (a `preset=`
    among them replaces the demo's); `unseen`: how many unseen robots to evaluate (default: 8 on a CPU, all of
    gen/test with an accelerator); `episode_length`: of the evaluation episodes (default: the run's); `video`: render
    one unseen robot's episode where OpenGL exists (the test leaves it to tests/test_render.py: ~35 s on 2 cores)."""
    cpu = jax.default_backend() == "cpu"
    base = CPU if cpu else ACCELERATOR
    if any(x.startswith("preset=") for x in extra):
        base = [x for x in base if not x.startswith("preset=")]
    cfg = compose_run_config(base + extra)
    what = (f"the CPU demo (preset=demo: {cfg.num_robots} robots, d_model {cfg.model.d_model}, "
            f"{cfg.total_steps:,} env steps)" if cpu else
            f"the accelerator configuration (R-MoMo, {cfg.total_steps:,} env steps on gen/train)")
    print(f"[demo] {jax.default_backend()} backend: {what}", flush=True)
    try:
        render.check_gl()
        no_video = None if video else "not asked for (video=False)"
    except render.RenderUnavailable as e:
        no_video = str(e)
    t0 = time.perf_counter()
    run_dir = train(cfg)
    loaded = load_run(run_dir)
    test = resolve_set(loaded.config, "test")
    unseen = unseen if unseen is not None else (UNSEEN_CPU if cpu else len(test.robots))
    test = dataclasses.replace(test, robots=test.robots[:unseen])
    episodes = 2 if cpu else 4
    evaluate_run(run_dir, ["train", test], episodes=episodes, zero_state_steps=0, episode_length=episode_length,
                 trace_steps=episode_length or 500)
    print("[demo] building the report (figures, tables, report.md)...", flush=True)
    report = build_report([run_dir], Path(run_dir) / "report", compare=[], title="mjx_morph demo")
    video = None
    if no_video is None:
        name = test.robots[0].name
        print(f"[demo] a video of {name} (unseen)...", flush=True)
        env = make_env_for(loaded.config, test.robots[:1])
        record = EpisodeRecorder(env, loaded.experiment.model, episode_length or loaded.config.env.episode_length,
                                 FAST_COMPILE if loaded.config.fast_compile else None)
        qpos, done = record(loaded.state.params, loaded.state.obs_rms, 0)
        video = Path(run_dir) / "videos" / f"{name}.mp4"
        render_video(env, 0, qpos[:episode_frames(done)], video)
    else:
        print(f"[demo] no video: {no_video}", flush=True)
    print(f"[demo] done in {(time.perf_counter() - t0) / 60:.1f} min. Outputs:\n"
          f"  learning curve   {Path(run_dir) / 'learning_curve.png'}\n"
          f"  zero-shot        {Path(run_dir) / 'eval'} (train.json, test.json)\n"
          f"  report           {report}\n"
          + (f"  video            {video}\n" if video else "")
          + f"  TensorBoard      tensorboard --logdir {Path(run_dir) / 'tb'}", flush=True)
    return Path(run_dir)


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    return cli.guarded(lambda: demo(argv))


if __name__ == "__main__":
    sys.exit(main())
