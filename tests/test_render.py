"""Policy videos (mjx_morph.eval.video, experiments.render) on a one-iteration smoke run: the rollout equals stepping
the env by hand, the video has one frame per state, the CLI writes it or exits 2 without an OpenGL backend.
Rendering tests skip with the reason when no OpenGL backend (EGL / OSMesa) is available."""
from __future__ import annotations

import warnings
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments import render as cli
from mjx_morph.eval import video
from mjx_morph.eval.sweep import episode_keys
from mjx_morph.layout import Obs
from mjx_morph.run import load_run
from mjx_morph.run import FAST_COMPILE
from mjx_morph.unimal import render
from mjx_morph.unimal.render import RenderUnavailable

ROOT = Path(__file__).resolve().parents[1]
STEPS = 20


@pytest.fixture(scope="module")
def run(smoke_run):
    d = smoke_run[0]
    run = load_run(d)
    cfg, env, model, ts = run.config, run.experiment.env, run.experiment.model, run.state
    record = video.EpisodeRecorder(env, model, STEPS, compiler_options=FAST_COMPILE)
    qpos, done = record(ts.params, ts.obs_rms, 1, seed=0)
    return d, cfg, env, model, ts, qpos, done


def test_rollout_matches_stepping_by_hand(run):
    _, _, env, model, ts, qpos, done = run
    assert qpos.shape == (STEPS, env.sm.mj_models[0].nq) and done.shape == (STEPS,)
    assert np.isfinite(qpos).all()
    n = video.episode_frames(done)
    assert np.linalg.norm(qpos[n - 1, :3] - qpos[0, :3]) > 1e-3          # the torso moves
    r = jnp.asarray([1], jnp.int32)
    reset = jax.jit(env.reset, compiler_options=FAST_COMPILE)          # eager: 5x slower than compiling
    state = reset(episode_keys(0, env, r, jnp.zeros((1,), jnp.int32))[0], r[0])
    carry = model.initial_carry(1)

    @partial(jax.jit, compiler_options=FAST_COMPILE)
    def act(state, carry, first):
        p = state.obs.proprio[None]
        obs = Obs(ts.obs_rms.normalize(p.reshape(1, -1)).reshape(p.shape), state.obs.prev_action[None],
                  state.obs.robot[None], state.obs.hfield[None])
        mu, _, carry = model.step(ts.params, env.robots, obs, carry, jnp.full((1,), first))
        return mu[0], carry

    step = jax.jit(env.step, compiler_options=FAST_COMPILE)
    for t in range(4):
        np.testing.assert_allclose(qpos[t], np.asarray(state.physics.qpos), atol=1e-4)
        mu, carry = act(state, carry, t == 0)
        state = step(state, mu)
        assert bool(state.done) == bool(done[t])


def test_find_robot(run):
    d, cfg, env, *_ = run
    assert video.find_robot(cfg, env, env.sm.names[1]) == (env, 1)
    e, i = video.find_robot(cfg, env, "gen-1-3")                             # held-out gen/test robot
    assert e.sm.names[i] == "gen-1-3" and e.num_robots == 100
    e, i = video.find_robot(cfg, env, str(ROOT / "assets/gen/test/xml/gen-1-4.xml"))
    assert e.sm.names == ["gen-1-4"] and i == 0
    with pytest.raises(ValueError, match="'gen-1-3' not found in the run's train set"):
        video.find_robot(cfg, env, "gen-1-3", robots="train")
    with pytest.raises(ValueError, match="not found"):
        video.find_robot(cfg, env, "no-such-robot")


def _read(path):
    import imageio_ffmpeg
    frames = imageio_ffmpeg.read_frames(str(path))
    with warnings.catch_warnings():         # JAX warns on any fork; ffmpeg's fork execs at once
        warnings.filterwarnings("ignore", r"os\.fork\(\) was called", RuntimeWarning)
        meta = next(frames)
    w, h = meta["size"]
    return meta, [np.frombuffer(f, np.uint8).reshape(h, w, 3) for f in frames]


def test_video_has_one_frame_per_state(run, tmp_path):
    _, _, env, _, _, qpos, done = run
    n = video.episode_frames(done)
    try:
        written = video.render_video(env, 1, qpos[:n], tmp_path / "v.mp4", width=160, height=120, fps=50)
    except RenderUnavailable as e:
        pytest.skip(str(e))
    meta, frames = _read(tmp_path / "v.mp4")
    assert written == n == len(frames) and meta["size"] == (160, 120) and meta["fps"] == 50
    centre = frames[0][30:90, 40:120].astype(float)
    assert abs(centre - np.array([.85, .5, .25]) * 255).sum(-1).min() < 60    # the orange robot in the middle


def test_cli_writes_video_or_exits_2_without_gl(run, tmp_path, monkeypatch, capsys):
    d, _, env, *_ = run
    name = env.sm.names[1]
    args = {"run_dir": str(d), "robot": name, "steps": STEPS, "width": 160, "height": 120, "fps": 25}
    try:
        out = cli.render_run(cli.RenderConfig(**args))
    except RenderUnavailable as e:
        pytest.skip(str(e))
    assert out == d / "videos" / f"{name}.mp4" and f"wrote {out}" in capsys.readouterr().out
    assert _read(out)[0]["fps"] == 25

    def no_gl(*_):
        raise RenderUnavailable("no OpenGL backend for offscreen rendering (test)")
    monkeypatch.setattr(render, "gl_context", no_gl)
    assert cli.main([f"{k}={v}" for k, v in {**args, "out": tmp_path / "x.mp4"}.items()]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: no OpenGL backend") and not (tmp_path / "x.mp4").exists()
