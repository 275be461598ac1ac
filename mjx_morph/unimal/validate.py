"""Design-space checks on `Morphology` values and on robot files.

`load_robot` already rejects files outside the UNIMAL format; `check_morphology` checks a value however it was made
(reader, generator, variants, user code): tree structure, limits and physically meaningful numbers. `validate_path`
runs both on files and also lists every value beyond the design space's plausibility bounds
(`design_space.outside_bounds`), as problems or, when the caller allows such robots, as warnings.
"""
from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from .design_space import outside_bounds
from .errors import RobotError
from .morphology import MAX_JOINTS_PER_LIMB, MAX_LIMBS, TORSO, Morphology
from .reader import load_robot, read_metadata, robot_files


def check_morphology(m: Morphology, where: str | None = None) -> list[str]:
    """Problems of a robot value, one message per problem (empty when it is inside the design space)."""
    w = where or m.name
    out: list[str] = []
    if not 1 <= m.num_limbs <= MAX_LIMBS:
        out.append(f"{w}: {m.num_limbs} limbs; expected 1 to {MAX_LIMBS}")
    if m.height <= 0:
        out.append(f"{w}: standing height {m.height} must be positive")
    if m.torso_density <= 0 or m.torso_radius <= 0:
        out.append(f"{w}: torso density and radius must be positive")
    ids = [l.id for l in m.limbs]
    if len(set(ids)) != len(ids):
        out.append(f"{w}: duplicate limb ids {ids}")
    for i, l in enumerate(m.limbs):
        lw = f"{w}: limb/{l.id}"
        if not (l.parent == TORSO or 0 <= l.parent < i):
            out.append(f"{lw}: parent index {l.parent} must be TORSO or an earlier limb (MuJoCo body order)")
        if l.radius <= 0 or l.density <= 0 or l.length <= 1e-6:
            out.append(f"{lw}: radius, density and capsule length must be positive")
        kinds = [j.kind for j in l.joints]
        if kinds not in (["x"], ["y"], ["x", "y"]) or len(kinds) > MAX_JOINTS_PER_LIMB:
            out.append(f"{lw}: joints {kinds}; expected x, y or x then y")
        for j in l.joints:
            jw = f"{w}: limb{j.kind}/{l.id}"
            lo, hi = j.range
            if not -180 <= lo < hi <= 180:
                out.append(f"{jw}: range ({lo}, {hi}) degrees; expected -180 <= lo < hi <= 180")
            if abs(np.linalg.norm(j.axis) - 1) > 1e-3:
                out.append(f"{jw}: axis {j.axis} is not a unit vector")
            if j.gear <= 0:
                out.append(f"{jw}: gear {j.gear} must be positive")
            if j.armature < 0 or j.damping < 0 or j.stiffness < 0:
                out.append(f"{jw}: armature, damping and stiffness must be >= 0")
    order: list[int] = []
    stack = list(reversed(m.children(TORSO)))
    while stack:
        i = stack.pop()
        order.append(i)
        stack += reversed(m.children(i))
    if order != list(range(m.num_limbs)):
        out.append(f"{w}: limbs are not in MuJoCo body order (depth-first, parents before children): {order}")
    for a, b in m.mirror_pairs:
        if a not in ids or b not in ids:
            out.append(f"{w}: mirror pair ({a}, {b}) names a limb that does not exist")
    return out


class Findings(NamedTuple):
    """What `validate_path` found, one line per item, each naming the file."""
    problems: list[str]     # errors: the file cannot be used as it is
    warnings: list[str]     # values outside the design space that the caller allowed
    outside: list[str]      # the lines about values outside the design space (in `problems` or `warnings`)


def validate_path(path: str | Path, *, allow_outside_design_space: bool = False) -> Findings:
    """Every problem of a robot file or of every file of a folder, metadata files included, each reported once.
    Values beyond the plausibility bounds (`design_space.outside_bounds`, all of them, not only the first) are
    problems, or warnings with `allow_outside_design_space`."""
    path = Path(path)
    try:
        files = [path] if path.is_file() else robot_files(path)
    except RobotError as e:
        return Findings([str(e)], [], [])
    problems: list[str] = []
    warnings: list[str] = []
    outside: list[str] = []
    for f in files:
        try:
            m = load_robot(f, allow_outside_design_space=True)
        except RobotError as e:
            problems.append(str(e))
            continue
        problems += check_morphology(m, str(f))
        beyond = [str(RobotError(str(f), element, message)) for element, message in
                  outside_bounds(m, skip_invalid=True)]
        outside += beyond
        if allow_outside_design_space:
            warnings += beyond
        else:
            problems += beyond
    if path.is_dir() and (path / "metadata").is_dir():
        stems = {f.stem for f in files}
        for meta in sorted((path / "metadata").glob("*.json")):
            if meta.stem not in stems:
                problems.append(f"{meta}: metadata without a robot file xml/{meta.stem}.xml")
                continue
            try:
                read_metadata(meta)
            except RobotError as e:
                if str(e) not in problems:          # not already reported by load_robot of its XML file
                    problems.append(str(e))
    return Findings(problems, warnings, outside)
