"""Plain NumPy implementation of the observation spec (MetaMorph's observation code), computed from MuJoCo C data.

Independent of mjx_morph.sim: it works on the robot *alone* (its own MJCF compiled by MuJoCo C), finds nodes and
joints by name like MetaMorph's agent.py, builds MetaMorph's padded height array H with NumPy slicing, and
indexes it with `pos_to_idx` and the rotated non-uniform mask. Used by tests/test_sim_obs.py.
"""
from __future__ import annotations

import math

import mujoco
import numpy as np
from scipy import signal

MAX_LIMBS = 12


# ---- proprioceptive observation and context ------------------------------------------------------------------------
def nodes(mm: mujoco.MjModel) -> list[int]:
    return [b for b in range(mm.nbody) if mujoco.mj_id2name(mm, mujoco.mjtObj.mjOBJ_BODY, b).startswith(("torso", "limb"))]


def _joint_slots(mm: mujoco.MjModel, body: int) -> dict[int, int]:
    out = {}
    for j in range(mm.njnt):
        if mm.jnt_bodyid[j] == body and mm.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE:
            name = mujoco.mj_id2name(mm, mujoco.mjtObj.mjOBJ_JOINT, j)
            out["xy".index(name.split("/")[0][-1])] = j
    return out


def _actuator_of(mm: mujoco.MjModel, j: int) -> int:
    return [a for a in range(mm.nu) if mm.actuator_trnid[a, 0] == j][0]


def proprio(mm: mujoco.MjModel, d: mujoco.MjData, origin=(0.0, 0.0, 0.0)) -> np.ndarray:
    """MetaMorph's proprioceptive observation of `d`; `origin`: MetaMorph's coordinates of the origin of `mm`'s world
    (positions are observed in MetaMorph's world)."""
    out = np.zeros((MAX_LIMBS, 52))
    bs = nodes(mm)
    torso_x = d.xpos[bs[0], 0]
    for i, b in enumerate(bs):
        g = mm.body_geomadr[b]
        xpos = d.xpos[b] + np.asarray(origin)
        xpos[0] = d.xpos[b, 0] - torso_x
        # mujoco-py's body_xvelp / body_xvelr: mj_jacBody (body frame origin) times qvel
        jacp, jacr = np.zeros((3, mm.nv)), np.zeros((3, mm.nv))
        mujoco.mj_jacBody(mm, d, jacp, jacr, b)
        limb = np.concatenate([xpos, jacp @ d.qvel, jacr @ d.qvel, d.xquat[b], mm.body_pos[b], mm.body_ipos[b], mm.body_iquat[b],
                               mm.geom_quat[g], [mm.body_mass[b]], mm.geom_size[g, :2]])
        joints = np.zeros(22)
        for k, j in _joint_slots(mm, b).items():
            lo, hi = mm.jnt_range[j]
            q = (d.qpos[mm.jnt_qposadr[j]] - lo) / (hi - lo)
            joints[11 * k:11 * (k + 1)] = np.concatenate([[q, d.qvel[mm.jnt_dofadr[j]]], mm.jnt_pos[j], mm.jnt_range[j],
                                                          mm.jnt_axis[j], [mm.actuator_gear[_actuator_of(mm, j), 0]]])
        out[i] = np.concatenate([limb, joints])
    return out


LIMB_CONTEXT = {
    "body_pos": ([-0.5, -0.45, -0.49], [0.5, 0.45, 2.04]),
    "body_ipos": ([-0.225, -0.225, -0.225], [0.225, 0.225, 0.0]),
    "body_iquat": ([0.70710678, -0.70710678, -0.70710678, 0.0], [1.0, 0.70710678, 0.70710678, 0.0]),
    "geom_quat": ([0.70710678, -0.70710678, -0.70710678, 0.0], [1.0, 0.70710678, 0.70710678, 0.0]),
    "body_mass": ([1.17809725], [4.1887902]),
    "body_shape": ([0.05, 0.0], [0.1, 0.22627417]),
}
JOINT_CONTEXT = {
    "jnt_pos": ([-0.05, -0.05, 0.0], [0.05, 0.05, 0.05]),
    "joint_range": ([-1.57079633, 0.0], [0.0, 1.57079633]),
    "joint_axis": ([-0.5000024, -0.5000024, -1.0], [1.0, 1.0, 1.0]),
    "gear": ([0.0], [300.0]),
}


def _norm(x, lo, hi):
    lo, hi = np.asarray(lo), np.asarray(hi)
    return -1.0 * (lo != hi) + 2.0 * (np.asarray(x) - lo) / (hi - lo + 1e-8)


def context(mm: mujoco.MjModel) -> np.ndarray:
    out = np.zeros((MAX_LIMBS, 35))
    for i, b in enumerate(nodes(mm)):
        g = mm.body_geomadr[b]
        vals = {"body_pos": mm.body_pos[b], "body_ipos": mm.body_ipos[b], "body_iquat": mm.body_iquat[b],
                "geom_quat": mm.geom_quat[g], "body_mass": [mm.body_mass[b]], "body_shape": mm.geom_size[g, :2]}
        limb = np.concatenate([_norm(vals[k], *LIMB_CONTEXT[k]) for k in LIMB_CONTEXT])
        joints = np.zeros(18)
        for k, j in _joint_slots(mm, b).items():
            jv = {"jnt_pos": mm.jnt_pos[j], "joint_range": mm.jnt_range[j], "joint_axis": mm.jnt_axis[j],
                  "gear": [mm.actuator_gear[_actuator_of(mm, j), 0]]}
            joints[9 * k:9 * (k + 1)] = np.concatenate([_norm(jv[n], *JOINT_CONTEXT[n]) for n in JOINT_CONTEXT])
        out[i] = np.concatenate([limb, joints])
    return out


def masks(mm: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """(node_mask True = real, act_mask True = real) in the contract's convention."""
    bs = nodes(mm)
    node = np.zeros(MAX_LIMBS, bool)
    node[:len(bs)] = True
    act = np.zeros(2 * MAX_LIMBS, bool)
    for i, b in enumerate(bs):
        for k in _joint_slots(mm, b):
            act[2 * i + k] = True
    return node, act


# ---- height arrays --------------------------------------------------------------------------------------------------
def corridor_H(seg_end, seg_kind, seg_height, seg_rug, band_end, band_f, band_clip) -> np.ndarray:
    """MetaMorph's H for csr (600 x 1300), from the corridor description (kinds 0 flat 1 curve 2 steps 3 rugged)."""
    H = np.zeros((400, 1100))
    start = 0
    for end, kind, c, rug in zip(seg_end, seg_kind, seg_height, seg_rug):
        ncol = int(end) - start
        if ncol > 0:
            if kind == 0:
                data = np.zeros((400, ncol))
            elif kind == 1:
                data = np.tile(c * np.sin(np.linspace(0, np.pi, num=ncol)), (400, 1))
            elif kind == 2:
                unit = ncol / 8
                heights = [round(h * 0.2, 2) for h in [0, 1, 2, 3, 2, 1, 0]]
                reps = [unit] * 7
                reps[3] *= 2
                data = np.tile(np.repeat(heights, np.asarray(reps, int)), (400, 1))
            else:
                data = np.zeros((400, ncol))
                idx = 0
                for b in range(band_end.shape[1]):
                    width = int(band_end[rug, b]) - idx
                    y = signal.sawtooth(np.linspace(0, band_f[rug, b] * np.pi, num=ncol), width=0.5) + 1
                    data[idx:idx + width, :] = np.clip(y, None, band_clip[rug, b])
                    idx += width
                    if idx >= 400:
                        break
            H[:, start:int(end)] = 1.0 + data
        start = int(end)
    H = np.pad(H, 100, mode="constant", constant_values=-10)
    return np.round(H, 3)


def obstacle_H(col, row, sx, sy, valid) -> np.ndarray:
    """MetaMorph's H for the obstacle env (620 x 1220): floor 1, walls 4 (10 cells), obstacles 3, gap -10."""
    H = np.ones((400, 1000))
    H = np.pad(H, 10, mode="constant", constant_values=4)
    H = np.pad(H, 100, mode="constant", constant_values=-10)
    H = np.round(H, 3)
    for c, r, a, b, v in zip(col, row, sx, sy, valid):
        if not v:
            continue
        R, C = pos_to_idx(H, 1, c, 400 - r)
        H[R - b:R + b, C - a:C + a] = 3.0
    return H


def pos_to_idx(H: np.ndarray, walls: int, col: int, row: int) -> tuple[int, int]:
    """Padded H index of unpadded cell (col, row) (row in H's orientation)."""
    pad = 100 + 10 * walls
    return row + pad, col + pad


def torso_idx(H: np.ndarray, walls: bool, x: float, y: float) -> tuple[int, int]:
    start = (3 + 10 + (1 if walls else 0)) * 10
    return int(H.shape[0] / 2 - math.floor(y * 10)), int(start + math.floor(x * 10))


def _non_uniform(end):
    p = np.asarray(list(range(0, end))) / end
    p = -1 * np.log(1 - p)
    p = (p / p[-1]) * end
    return np.unique(p.astype(int))


def _range(low, hi):
    pts = _non_uniform(hi)
    if low > 0:
        pts = np.concatenate((np.flip(-1 * _non_uniform(low)), pts))
    return np.unique(pts)


def hfield_obs(H: np.ndarray, walls: bool, x: float, y: float, x_dir: np.ndarray | None) -> np.ndarray:
    """The 1410 values; x_dir = torso x-axis in the xy plane (None: axis-aligned, as after a reset)."""
    xs = _range(10, 40)
    ys = _range(40, 40)
    col, row = np.meshgrid(xs, ys)
    if x_dir is not None:
        x_dir = x_dir / np.linalg.norm(x_dir)
        a = np.arctan2(np.linalg.det(np.stack(([1, 0], x_dir))), np.dot([1, 0], x_dir))
        xr = np.cos(a) * col + np.sin(a) * row
        yr = -np.sin(a) * col + np.cos(a) * row
        row, col = np.around(yr).astype(int), np.around(xr).astype(int)
    r, c = torso_idx(H, walls, x, y)
    return (H[row + r, col + c] - H[r, c]).flatten()


def available_robots():
    """The shipped generated robots, else the original train robots; skips the test when neither is there."""
    import pytest

    from mjx_morph.unimal.sets import load_set, unimals_root
    try:
        rs = load_set("gen/train").robots
    except Exception:
        rs = ()
    if not rs:
        if unimals_root() is None:
            pytest.skip("no robots available: neither assets/gen/train nor ../shared/unimals_100 "
                        "(set MJX_MORPH_UNIMALS)")
        rs = load_set("unimal100/train").robots
    return rs
