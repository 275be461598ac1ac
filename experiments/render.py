"""A video of a trained policy: `python -m experiments.render run_dir=<dir> robot=<name> [out=<file.mp4>]`.

    python -m experiments.render run_dir=runs/ft-rmomo-s0 robot=gen-0-5                 # a train or test robot
    python -m experiments.render run_dir=runs/ft-rmomo-s0 robot=gen-1-3 robots=test steps=500
    python -m experiments.render run_dir=runs/ft-rmomo-s0 robot=path/to/robot.xml out=robot.mp4 fps=25

One deterministic episode (the evaluation's episode 0 of that robot for `seed`), up to its end or `steps` control
steps, rendered offscreen with a camera following the torso (see mjx_morph.eval.video). Needs an OpenGL backend
(EGL or OSMesa; `MUJOCO_GL` picks one); without one it exits with status 2 and says what to install, before it
loads the run or compiles anything (`unimal.render.check_gl`).
"""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path
from typing import Optional

from omegaconf import MISSING

from mjx_morph.eval.video import EpisodeRecorder, episode_frames, find_robot, render_video
from mjx_morph.run import FAST_COMPILE, load_run, register
from mjx_morph.unimal.render import check_gl

from . import cli


@dataclasses.dataclass
class RenderConfig:
    run_dir: str = MISSING          # a run directory of experiments.run
    robot: str = MISSING            # a robot name (looked up in the run's train set, then its test set) or an XML file
    robots: Optional[str] = None    # look the name up in this set instead (train | val | test | variants | any set)
    out: Optional[str] = None       # None: <run_dir>/videos/<robot>.mp4
    steps: int = 1000               # at most this many control steps; the video stops at the first episode end
    seed: int = 0                   # episode 0 of the robot with this seed: the same episode as experiments.evaluate's
    step: Optional[int] = None      # checkpoint (iteration); None: the newest
    width: int = 640                # frame size (even numbers)
    height: int = 480
    fps: float = 50.0               # 50 = real time (control dt 0.02 s)


register("render_schema", RenderConfig)


def render_run(c: RenderConfig) -> Path:
    if c.width % 2 or c.height % 2 or min(c.width, c.height) <= 0:
        raise ValueError(f"width={c.width} height={c.height}: the frame size must be positive and even (H.264)")
    check_gl()                                # no OpenGL backend: say so now, not after loading and compiling
    t0 = time.perf_counter()
    loaded = load_run(c.run_dir, c.step)
    cfg, exp = loaded.config, loaded.experiment
    env, index = find_robot(cfg, exp.env, str(c.robot), c.robots)
    name = env.sm.names[index]
    out = Path(c.out or Path(c.run_dir) / "videos" / f"{name}.mp4")
    print(f"[mjx_morph] {name}: compiling and running the episode ({c.steps} control steps)...", flush=True)
    record = EpisodeRecorder(env, exp.model, c.steps, compiler_options=FAST_COMPILE if cfg.fast_compile else None)
    qpos, done = record(loaded.state.params, loaded.state.obs_rms, index, c.seed)
    n = episode_frames(done)
    print(f"[mjx_morph] rendering {n} frames...", flush=True)
    n_frames = render_video(env, index, qpos[:n], out, seed=c.seed, width=c.width, height=c.height, fps=c.fps)
    end = f"episode ended after {n} steps" if done.any() else f"episode still running after {n} steps"
    print(f"[mjx_morph] wrote {out}: {name}, checkpoint {loaded.step}, {n_frames} frames at {c.fps:g} fps ({end}; "
          f"{time.perf_counter() - t0:.0f} s)", flush=True)
    return out


def main(argv=None) -> int:
    return cli.main(render_run, "render_schema", RenderConfig, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
