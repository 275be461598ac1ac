"""Videos of a trained policy: one deterministic episode of one robot, rendered offscreen with MuJoCo.

    env, index = find_robot(cfg, run_env, "gen-1-3")          # a robot of the run's train or test set, or a file
    record = EpisodeRecorder(env, model, steps=1000)          # compiled once, for any robot of env
    qpos, done = record(params, obs_rms, index, seed=0)
    n = episode_frames(done)                                   # frames up to the first episode end
    render_video(env, index, qpos[:n], "robot.mp4", seed=0, width=640, height=480, fps=50)

Rollout (`EpisodeRecorder`): the evaluation sweep's (`sweep.Sweeper`) for a single env, in one jitted `lax.scan`:
reset with the key of episode 0 of `robot_index` (`sweep.episode_keys`), observations normalised with the run's
frozen statistics, the Gaussian's mean as the action, the recurrent state reset at t = 0. In the env of a robot
set the video therefore shows episode 0 of `experiments.evaluate` for that robot with the same seed. `qpos[t]` is
the physics state *before* step t (`qpos[0]` the reset pose) in the padded shared-tree layout, `done[t]` whether
step t ended the episode. The env resets itself in the step that ends an episode, so the terminal state is not
kept: the video shows qpos[0 .. k] for the first step k that ends the episode (`episode_frames`), all `steps`
states if none does.

Rendering: the robot's padded MJCF (`sim.padding`, the text `env.sm.mj_models[i]` was compiled from, so the env's
qpos goes straight into its MjData) plus a checker floor, a sky and the gallery's light (`unimal.render`), drawn
with `unimal.render.OffscreenRenderer`; the camera looks at the torso from the side (-y, the robot walks toward +x,
to the right of the picture), its height smoothed against the torso's bounce, at a distance from the robot's size.
Terrain: ft and incline are the physics' own infinite planes. csr and obstacle simulate a small height-field patch
that moves with the torso (`sim.terrain`); the video draws a larger one (12 m square) filled from the same terrain
function (`env.terrain.patch`), re-centred in 2 m jumps so that its checker stays fixed to the ground: the ground
within ~5 m of the torso is exactly what the robot stands on, nothing farther is drawn.
Frames are streamed to ffmpeg (`imageio-ffmpeg`), so a long video never sits in memory.
"""
from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path
from typing import Iterable, Iterator

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from ..nets.model import Model
from ..sim import padding
from ..sim.terrain import grid
from ..sim.env import Env
from ..run import FAST_COMPILE, RunConfig, make_env_for
from ..unimal import render
from ..unimal.reader import load_robot
from ..unimal.errors import RobotError
from .evaluate import resolve_set
from .sweep import episode_keys, policy_step

RENDER_PATCH = 121       # height-field vertices per side drawn for csr / obstacle (0.1 m apart: 12 m)


class EpisodeRecorder:
    """Episode 0 of one robot of `env` under the deterministic policy of `model` (see the module docstring):
    `recorder(params, obs_rms, robot_index, seed)` -> (qpos (steps, nq), done (steps,)). The rollout is jitted
    once per recorder and serves every robot of the env: keep one recorder per (env, model, steps)."""

    def __init__(self, env: Env, model: Model, steps: int = 1000, compiler_options: dict | None = None):
        self.env, self.model, self.steps = env, model, int(steps)
        self._run = jax.jit(self._rollout, compiler_options=compiler_options)

    def _rollout(self, params, obs_rms, robot, key):
        env, model = self.env, self.model
        cache = model.robot_cache(params, env.robots)
        state = env.vreset(key[None], robot[None])

        def body(c, t):
            state, carry = c
            nxt, carry = policy_step(env, model, params, obs_rms, cache, state, carry, jnp.full((1,), t == 0))
            return (nxt, carry), (state.physics.qpos[0], nxt.done[0])

        _, (qpos, done) = jax.lax.scan(body, (state, model.initial_carry(1)), jnp.arange(self.steps))
        return qpos, done

    def __call__(self, params, obs_rms, robot_index: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
        if not 0 <= robot_index < self.env.num_robots:
            raise ValueError(f"robot index {robot_index} not in [0, {self.env.num_robots})")
        r = jnp.asarray([robot_index], jnp.int32)
        key = episode_keys(seed, self.env, r, jnp.zeros((1,), jnp.int32))[0]
        qpos, done = self._run(params, obs_rms, r[0], key)
        return np.asarray(qpos), np.asarray(done)


def find_robot(cfg: RunConfig, run_env: Env, robot: str, robots: str | None = None) -> tuple[Env, int]:
    """(env, robot index) for `robot` of a run with config `cfg` and train env `run_env`: a robot name looked up in
    the set `robots` (a name of `experiments.evaluate`) if given, else in the run's train set (`run_env` itself),
    then in its held-out `test` set; or a robot XML file, alone in its own env. A set other than the train set gets
    its own env (the robots' shared tree, as `experiments.evaluate` builds it)."""
    path = Path(robot).expanduser()
    if robots is None and (path.suffix == ".xml" or path.is_file()):
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such robot file")
        return make_env_for(cfg, [load_robot(path)]), 0
    names = list(run_env.sm.names)
    looked = []
    if robots in (None, "train"):
        if robot in names:
            return run_env, names.index(robot)
        looked.append(f"the run's train set ({len(names)} robots)")
    if robots != "train":
        try:
            es = resolve_set(cfg, robots or "test")
        except (ValueError, RobotError) as e:
            if robots is not None:
                raise
            es = None
            looked.append(f"no test set ({e})")
        if es is not None:
            found = [m.name for m in es.robots]
            if robot in found:
                return make_env_for(cfg, es.robots), found.index(robot)
            looked.append(f"{es.name} ({len(found)} robots)")
    raise ValueError(f"robot {robot!r} not found in " + "; ".join(looked) + f". Give a robot name (e.g. "
                     f"{names[0]!r}), robots=<set> to look in another set, or a robot XML file")


def episode_frames(done: np.ndarray) -> int:
    """Number of states of the first episode in a rollout (all of them if it did not end)."""
    ends = np.flatnonzero(done)
    return int(ends[0]) + 1 if ends.size else len(done)


# a sky, and the height field's checker: 6 tiles of 2 x 2 squares over the 12 m patch, i.e. 1 m squares
_SCENE = """
  <asset>
    <texture type="skybox" builtin="gradient" rgb1=".45 .55 .65" rgb2=".05 .05 .1" width="64" height="64"/>
    <material name="hgrid" texture="grid" texrepeat="6 6"/>
  </asset>
"""
SNAP = 20                # cells: the drawn patch moves in 2 m jumps, so its checker stays fixed to the ground


def _render_terrain(env: Env):
    """The env's height-field terrain with the larger patch the video draws."""
    return dataclasses.replace(env.terrain, patch_size=RENDER_PATCH)


def render_model(env: Env, robot_index: int) -> mujoco.MjModel:
    """MuJoCo model to draw robot `robot_index` of `env` in: its padded MJCF with a textured ground, a sky and
    the gallery's light (a larger height field for csr / obstacle); the qpos layout of
    `env.sm.mj_models[robot_index]`."""
    sm = env.sm
    world = _render_terrain(env).world() if env.task.uses_hfield else sm.world
    xml = padding.padded_mjcf(sm.robots[robot_index], sm.tree, robot_index, world, sm.options)
    xml = xml.replace('type="plane"', 'type="plane" material="grid"').replace(
        'type="hfield"', 'type="hfield" material="hgrid"')
    mm = mujoco.MjModel.from_xml_string(xml.replace("</mujoco>", render._LOOK + _SCENE + "</mujoco>"))
    ref = sm.mj_models[robot_index]
    if (mm.nq, mm.nbody, mm.ngeom) != (ref.nq, ref.nbody, ref.ngeom):
        raise RuntimeError("render model does not match the env's model")   # padding.py changed shape
    mm.geom_rgba[mm.body_geomadr[1:]] = (.85, .5, .25, 1)                  # the robot in the gallery's colour
    return mm


def _patch_centre(x: float, y: float) -> tuple[float, float]:
    """A point in the cell nearest to (x, y) whose indices are multiples of SNAP."""
    c, r = (round(float(v) / SNAP) * SNAP for v in grid.cell_of(jnp.float32(x), jnp.float32(y)))
    return (c - grid.START_COL + 0.5) / grid.DIVS, (grid.HALF_ROWS - r + 0.5) / grid.DIVS


def render_frames(env: Env, robot_index: int, qpos: np.ndarray, seed: int = 0, width: int = 640,
                  height: int = 480, azimuth: float = 90.0, elevation: float = -20.0) -> Iterator[np.ndarray]:
    """RGB frames (height, width, 3) uint8 of the states `qpos` (T, nq) of episode 0 of `robot_index` (the
    episode's terrain comes from `seed`). Raises `unimal.render.RenderUnavailable` without an OpenGL backend."""
    mm = render_model(env, robot_index)
    data = mujoco.MjData(mm)
    m = env.sm.robots[robot_index]
    extent = float(np.abs(m.rest_positions() - [0, 0, m.height]).max(initial=0.3)) + 0.5
    distance = 2.2 * extent + 0.8
    mm.vis.map.znear, mm.vis.map.zfar = 0.02 / mm.stat.extent, 200.0 / mm.stat.extent   # in units of the extent
    shown = None
    if env.task.uses_hfield:
        r = jnp.asarray([robot_index], jnp.int32)
        reset = jax.jit(env.reset, compiler_options=FAST_COMPILE)      # compiled: 5x faster than eager
        ts = reset(episode_keys(seed, env, r, jnp.zeros((1,), jnp.int32))[0], r[0]).episode.terrain
        fill = jax.jit(lambda x, y: _render_terrain(env).patch(ts, x, y))
        hgeom = int(np.nonzero(mm.geom_type == mujoco.mjtGeom.mjGEOM_HFIELD)[0][0])
    renderer = render.OffscreenRenderer(mm, width, height)
    try:
        z = None
        for q in np.asarray(qpos):
            data.qpos[:] = q
            if env.task.uses_hfield:
                centre = _patch_centre(q[0], q[1])
                if centre != shown:
                    hdata, pos = jax.device_get(fill(*map(jnp.float32, centre)))
                    mm.hfield_data[:] = hdata
                    mm.geom_pos[hgeom] = pos
                    renderer.ctx.make_current()
                    mujoco.mjr_uploadHField(mm, renderer.con, 0)
                    shown = centre
            mujoco.mj_kinematics(mm, data)
            torso = data.xpos[1].copy()
            z = torso[2] if z is None else 0.9 * z + 0.1 * torso[2]
            yield renderer.render(data, lookat=[torso[0], torso[1], z], distance=distance, azimuth=azimuth,
                                  elevation=elevation)
    finally:
        renderer.close()


def write_mp4(frames: Iterable[np.ndarray], path: str | Path, fps: float = 50.0) -> int:
    """Encode RGB frames (all of one even size) as H.264 mp4 with imageio-ffmpeg's bundled ffmpeg; returns the
    number of frames written. Nothing is left at `path` if the frames fail."""
    import imageio_ffmpeg
    path = Path(path)
    writer, n = None, 0
    try:
        for f in frames:
            if writer is None:
                h, w = f.shape[:2]
                if h % 2 or w % 2:
                    raise ValueError(f"frame size {w}x{h}: width and height must be even for H.264 (yuv420p)")
                path.parent.mkdir(parents=True, exist_ok=True)
                writer = imageio_ffmpeg.write_frames(str(path), (w, h), fps=fps, macro_block_size=2,
                                                     ffmpeg_log_level="error")
                with warnings.catch_warnings():   # JAX warns on any fork; ffmpeg's fork execs at once
                    warnings.filterwarnings("ignore", r"os\.fork\(\) was called", RuntimeWarning)
                    writer.send(None)
            writer.send(np.ascontiguousarray(f, dtype=np.uint8))
            n += 1
    except BaseException:
        if writer is not None:
            writer.close()
            writer = None
            path.unlink(missing_ok=True)
        raise
    finally:
        if writer is not None:
            writer.close()
        if hasattr(frames, "close"):
            frames.close()                    # a generator's renderer (GL context) is freed now
    if n == 0:
        raise ValueError("no frames to write")
    return n


def render_video(env: Env, robot_index: int, qpos: np.ndarray, path: str | Path, seed: int = 0,
                 width: int = 640, height: int = 480, fps: float = 50.0) -> int:
    """Render the states `qpos` of robot `robot_index` and write them to `path` (mp4); returns the frame count.
    fps 50 is real time (control dt 0.02 s)."""
    return write_mp4(render_frames(env, robot_index, qpos, seed, width, height), path, fps)
