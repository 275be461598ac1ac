"""Named robot sets and where they come from.

| name              | robots | source |
|-------------------|--------|--------|
| `unimal100/train` | 100    | the original MetaMorph train robots |
| `unimal100/test`  | 102    | the original test robots (4 of them are byte-identical to train robots) |
| `unimal100/val`   | 32     | our fixed split of `unimal100/test` (see `split_test`) |
| `unimal100/test70`| 70     | the rest of that split |
| `gen/train`       | 100    | the project's own generated robots, shipped in `assets/gen/train` (embedded default) |
| `gen/test`        | 100    | generated robots whose topologies are not in `gen/train` |
| `<set>/variants`  | 24/robot | dynamics and kinematics variants of a set (`<set>/variants/<change>` for one change type) |

Anything else is taken as a path: a MetaMorph folder (`xml/` + `metadata/`), a folder of XML files, or one XML file.
Robot files with values far beyond the design space (`design_space.outside_bounds`) are refused unless the caller
allows them (`load_set(..., allow_outside_design_space=True)`).

The original robots are data, never committed: they are read from the folder given by `root=`, else the
`MJX_MORPH_UNIMALS` environment variable, else `../shared/unimals_100` beside the project when it exists.

The R-MoMo paper splits the 102 test robots into 32 validation and 70 test robots but publishes no list. Our split
(a reconstruction): sort the 102 ids, permute them with `numpy.random.default_rng(0)`, the first 32 are `val`, the
other 70 `test70`. The 4 ids shared with the train set are kept (32 + 70 = 102 says the paper kept them too).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import RobotError
from .morphology import Morphology
from .reader import load_folder, load_robot
from .variants import CHANGE_TYPES, make_variants

PROJECT_ROOT = Path(__file__).resolve().parents[2]
ASSETS = PROJECT_ROOT / "assets"
SPLIT_SEED = 0
NUM_VAL = 32
ORIGINAL_SETS = ("train", "test", "val", "test70")
GENERATED_SETS = ("train", "test")


@dataclass(frozen=True)
class RobotSet:
    name: str
    robots: tuple[Morphology, ...]
    source: str  # folder or file the robots were read from

    def __len__(self) -> int:
        return len(self.robots)

    @property
    def names(self) -> list[str]:
        return [m.name for m in self.robots]


def unimals_root(root: str | Path | None = None) -> Path | None:
    """Folder of the original robots, or None when it is not available."""
    for cand in (root, os.environ.get("MJX_MORPH_UNIMALS"), PROJECT_ROOT.parent / "shared" / "unimals_100"):
        if cand:
            p = Path(cand).expanduser()
            if (p / "train").is_dir():
                return p
            if root is not None and cand is root:
                raise RobotError(str(p), "", "not a unimals_100 folder (expected train/ and test/ inside)")
    return None


def split_test(ids: list[str], seed: int = SPLIT_SEED, num_val: int = NUM_VAL) -> tuple[list[str], list[str]]:
    """The fixed val/test70 split of the original test ids."""
    ids = sorted(ids)
    order = np.random.default_rng(seed).permutation(len(ids))
    chosen = [ids[i] for i in order]
    return sorted(chosen[:num_val]), sorted(chosen[num_val:])


def load_set(name: str, root: str | Path | None = None, *, allow_outside_design_space: bool = False) -> RobotSet:
    """Robots of a named set or a path (see the module docstring). A robot file with values far beyond the design
    space (`design_space.outside_bounds`) raises `RobotError` unless `allow_outside_design_space`; every robot of
    the named sets and their variants is inside."""
    allow = allow_outside_design_space
    if name.endswith("/variants") or "/variants/" in name:
        base, _, change = name.partition("/variants")
        change = change.strip("/")
        if change and change not in CHANGE_TYPES:
            raise RobotError(name, "", f"unknown change type {change!r}; expected one of {', '.join(CHANGE_TYPES)}")
        parent = load_set(base, root, allow_outside_design_space=allow)
        robots = make_variants(parent.robots, types=(change,) if change else CHANGE_TYPES)
        return RobotSet(name, tuple(robots), parent.source)
    head, _, tail = name.partition("/")
    if head == "unimal100" and tail in ORIGINAL_SETS:
        base = unimals_root(root)
        if base is None:
            raise RobotError(name, "", "the original robots are not available: set MJX_MORPH_UNIMALS or robots_root "
                             "to a unimals_100 folder (with train/ and test/), or use gen/train")
        if tail in ("train", "test"):
            return RobotSet(name, tuple(load_folder(base / tail, allow_outside_design_space=allow)), str(base / tail))
        test = load_folder(base / "test", allow_outside_design_space=allow)
        val_ids, test_ids = split_test([m.name for m in test])
        keep = set(val_ids if tail == "val" else test_ids)
        return RobotSet(name, tuple(m for m in test if m.name in keep), str(base / "test"))
    if head == "gen" and tail in GENERATED_SETS:
        folder = ASSETS / "gen" / tail
        return RobotSet(name, tuple(load_folder(folder, allow_outside_design_space=allow)), str(folder))
    path = Path(name).expanduser()
    if path.is_file():
        return RobotSet(path.stem, (load_robot(path, allow_outside_design_space=allow),), str(path))
    if path.is_dir():
        return RobotSet(path.name, tuple(load_folder(path, allow_outside_design_space=allow)), str(path))
    raise RobotError(name, "", "not a robot set or path; known sets: "
                     + ", ".join([f"unimal100/{s}" for s in ORIGINAL_SETS] + [f"gen/{s}" for s in GENERATED_SETS])
                     + ", <set>/variants[/<change>]")


def default_train_set(root: str | Path | None = None) -> str:
    """`unimal100/train` when the original robots are available, else the shipped `gen/train`."""
    return "unimal100/train" if unimals_root(root) is not None else "gen/train"
