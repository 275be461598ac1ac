"""Write a `Morphology` as MJCF, and save robots in MetaMorph format (xml/ + metadata/).

`to_mjcf` writes the robot the way the environments use it: the DERL template's options and defaults (timestep
0.005, parent-child contact filtering on as MetaMorph sets it, capsule geoms with friction 0.7), the torso subtree
and one motor per joint; no sensors, cameras, lights, materials or contact excludes. Every joint writes its
armature, damping and stiffness explicitly, so variants that change them need no extra classes.
With `sites=True` it also writes DERL's growth and `btm_pos` sites, so that the files stay readable by the
original MetaMorph/DERL tooling (used by `save_robot`).
"""
from __future__ import annotations

import json
from pathlib import Path
from xml.sax.saxutils import quoteattr

import mujoco
import numpy as np

from .morphology import TORSO, Morphology


def format_number(x: float) -> str:
    """Shortest text that reads back as the same float64 (no precision is lost in a round trip)."""
    x = float(x)
    if x == 0.0:
        return "0"
    r = repr(x)
    return r[:-2] if r.endswith(".0") else r


def format_vector(v) -> str:
    """The numbers of `v`, each as `format_number` writes it, separated by spaces."""
    return " ".join(format_number(x) for x in v)


_num, _vec = format_number, format_vector     # short names for this module's f-strings


def limb_inertial(l) -> str:
    """The `<inertial>` element of a limb's body: MetaMorph's capsule mass and inertia (`Limb.mass`), which MuJoCo
    >= 2.1.2 no longer computes from the geom, in the geom's own frame. MuJoCo 2.0 gave a body of one geom that
    geom's frame as its inertial frame (`body_iquat` = `geom_quat`), and both are context features whose 4th
    component ModuMorph's bounds fix at 0; a `fullinertia` would let the compiler pick any principal frame of the
    two equal moments (it did for 566 of the 807 train limbs, e.g. iquat (0.5, 0.5, 0.5, 0.5): contexts up to
    1e8, and session 44's R-MeMo run never learnt)."""
    tip = np.asarray(l.tip, np.float64)
    quat = np.zeros(4)
    mujoco.mju_quatZ2Vec(quat, -tip)                    # the frame MuJoCo gives the geom: z along from - to
    return (f'<inertial pos="{_vec(tip / 2.0)}" quat="{_vec(quat)}" mass="{_num(l.mass)}" '
            f'diaginertia="{_vec(l.principal_inertia())}"/>')


def to_mjcf(m: Morphology, *, sites: bool = False, floor: bool = False, z_offset: float = 0.0,
            inertials: bool = False) -> str:
    """MJCF text for one robot. `floor` adds a plane at z = 0 (for stand-alone checks); `z_offset` raises the
    torso (MetaMorph's worlds put the floor top at z = 1; ours at 0, sim/terrain); `inertials` gives each limb
    MetaMorph's mass and inertia (`limb_inertial`; what the simulation compiles), without them MuJoCo computes its
    own from the capsule (the robot files, as UNIMAL writes them)."""
    lines = [
        f"<mujoco model={quoteattr(m.name)}>",
        '  <compiler angle="degree"/>',
        '  <option timestep="0.005">',
        '    <flag filterparent="enable"/>',
        "  </option>",
        "  <default>",
        '    <motor ctrlrange="-1 1" ctrllimited="true"/>',
        '    <joint type="hinge" limited="true" solimplimit="0 0.99 0.01"/>',
        '    <geom type="capsule" condim="3" friction="0.7 0.1 0.1"/>',
        '    <site size="1e-6 1e-6 1e-6"/>',
        "  </default>",
        "  <worldbody>",
    ]
    if floor:
        lines.append('    <geom name="floor" type="plane" size="50 50 0.1" pos="0 0 0"/>')
    lines += [
        f'    <body name="torso/0" pos="0 0 {_num(m.height + z_offset)}">',
        '      <freejoint name="root"/>',
        f'      <geom name="torso/0" type="sphere" size="{_num(m.torso_radius)}" density="{_num(m.torso_density)}"/>',
    ]
    if sites:
        lines += ['      <site name="torso/0" pos="0 0 0"/>',
                  f'      <site name="torso/btm_pos/0" pos="0 0 {_num(-m.torso_radius)}"/>']

    def write(index: int, indent: str) -> None:
        l = m.limbs[index]
        lines.append(f'{indent}<body name="limb/{l.id}" pos="{_vec(l.pos)}">')
        for j in l.joints:
            lines.append(
                f'{indent}  <joint name="limb{j.kind}/{l.id}" pos="{_vec(j.pos)}" axis="{_vec(j.axis)}" '
                f'range="{_vec(j.range)}" armature="{_num(j.armature)}" damping="{_num(j.damping)}" '
                f'stiffness="{_num(j.stiffness)}"/>')
        lines.append(f'{indent}  <geom name="limb/{l.id}" fromto="0 0 0 {_vec(l.tip)}" size="{_num(l.radius)}" '
                     f'density="{_num(l.density)}"/>')
        if inertials:
            lines.append(f"{indent}  {limb_inertial(l)}")
        if sites:
            # DERL's sites: v(r + h/2), v(r + h) and v(2r + h) along the limb, each component rounded to 2
            # decimals; the segment length r + h is the nominal one (0.25/0.35/0.45), not |tip| of the rounded tip
            tip = np.asarray(l.tip)
            unit = tip / np.linalg.norm(tip)
            seg = round(float(np.linalg.norm(tip)) / 0.05) * 0.05
            site = lambda d: _vec(np.round(d * unit, 2) + 0.0)
            lines.extend([f'{indent}  <site name="limb/mid/{l.id}" pos="{site((seg + l.radius) / 2)}"/>',
                          f'{indent}  <site name="limb/btm/{l.id}" pos="{_vec(tip)}"/>',
                          f'{indent}  <site name="limb/btm_pos/{l.id}" pos="{site(seg + l.radius)}"/>'])
        for c in m.children(index):
            write(c, indent + "  ")
        lines.append(f"{indent}</body>")

    for c in m.children(TORSO):
        write(c, "      ")
    lines += ["    </body>", "  </worldbody>", "  <actuator>"]
    for i, j in m.joints():
        name = f"limb{j.kind}/{m.limbs[i].id}"
        lines.append(f'    <motor name="{name}" joint="{name}" gear="{_num(j.gear)}"/>')
    lines += ["  </actuator>", "</mujoco>", ""]
    return "\n".join(lines)


def compile_model(m: Morphology, *, inertials: bool = True, **kwargs) -> mujoco.MjModel:
    """Compile the robot with MuJoCo, by default with MetaMorph's limb masses (kwargs go to `to_mjcf`)."""
    return mujoco.MjModel.from_xml_string(to_mjcf(m, inertials=inertials, **kwargs))


def metadata(m: Morphology) -> dict:
    """MetaMorph's metadata JSON for a robot."""
    return {"symmetric_limbs": [list(p) for p in m.mirror_pairs], "dof": m.dof, "num_limbs": m.num_limbs}


def save_robot(m: Morphology, folder: str | Path) -> Path:
    """Write `folder/xml/<name>.xml` and `folder/metadata/<name>.json` (MetaMorph format). Returns the XML path."""
    folder = Path(folder)
    (folder / "xml").mkdir(parents=True, exist_ok=True)
    (folder / "metadata").mkdir(parents=True, exist_ok=True)
    path = folder / "xml" / f"{m.name}.xml"
    path.write_text(to_mjcf(m, sites=True))
    (folder / "metadata" / f"{m.name}.json").write_text(json.dumps(metadata(m), indent=2) + "\n")
    return path


def save_set(robots, folder: str | Path) -> list[Path]:
    return [save_robot(m, folder) for m in robots]
