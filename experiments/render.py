"""A video of a trained policy: `python -m experiments.render run_dir=<dir> robot=<name> [out=<file.mp4>]`.

    python -m experiments.render run_dir=runs/ft-rmomo-s0 robot=gen-0-5                 # a train or test robot
    python -m experiments.render run_dir=runs/ft-rmomo-s0 robot=gen-1-3 robots=test steps=500
    python -m experiments.render run_dir=runs/ft-rmomo-s0 robot=path/to/robot.xml out=robot.mp4 fps=25

One deterministic episode (the evaluation's episode 0 of that robot for `seed`), up to its end or `steps` control
steps, rendered offscreen with a camera following the torso (see mjx_morph.eval.video). Needs an OpenGL backend
(EGL or OSMesa; `MUJOCO_GL` picks one); without one it exits with status 2 and says what to install.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from mjx_morph.ppo.run_dir import RunDirError
from mjx_morph.unimal.errors import RobotError
from mjx_morph.unimal.render import RenderUnavailable


def render_run(c: dict) -> Path:
    from mjx_morph.eval.video import EpisodeRecorder, episode_frames, find_robot, render_video
    from mjx_morph.ppo.loop import load_run
    from mjx_morph.ppo.trainer import FAST_COMPILE
    if int(c["width"]) % 2 or int(c["height"]) % 2 or min(int(c["width"]), int(c["height"])) <= 0:
        raise ValueError(f"width={c['width']} height={c['height']}: the frame size must be positive and even (H.264)")
    t0 = time.perf_counter()
    cfg, run_env, model, _, ts, step = load_run(c["run_dir"], c["step"])
    env, index = find_robot(cfg, run_env, str(c["robot"]), c["robots"])
    name = env.sm.names[index]
    out = Path(c["out"] or Path(c["run_dir"]) / "videos" / f"{name}.mp4")
    record = EpisodeRecorder(env, model, int(c["steps"]),
                             compiler_options=FAST_COMPILE if cfg.get("fast_compile") else None)
    qpos, done = record(ts.params, ts.obs_rms, index, int(c["seed"]))
    n = episode_frames(done)
    n_frames = render_video(env, index, qpos[:n], out, seed=int(c["seed"]), width=int(c["width"]),
                            height=int(c["height"]), fps=float(c["fps"]))
    end = f"episode ended after {n} steps" if done.any() else f"episode still running after {n} steps"
    print(f"[mjx_morph] wrote {out}: {name}, checkpoint {step}, {n_frames} frames at {c['fps']} fps ({end}; "
          f"{time.perf_counter() - t0:.0f} s)", flush=True)
    return out


def run(c: dict) -> int:
    """`render_run` with user errors (no OpenGL backend included) reported as `error: ...` and status 2."""
    try:
        render_run(c)
    except (RenderUnavailable, RunDirError, RobotError, ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


@hydra.main(config_path="conf", config_name="render", version_base=None)
def main(cfg: DictConfig) -> None:
    code = run(OmegaConf.to_container(cfg, resolve=True))
    if code:
        sys.exit(code)


if __name__ == "__main__":
    main()
