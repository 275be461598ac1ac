"""Make the generated robot sets shipped in assets/ (deterministic; re-running rewrites identical files).

    python -m experiments.make_assets [--out assets/gen]

- `assets/gen/train`: 100 robots `gen-0-<i>` = `generate_set(100, seed=TRAIN_SEED)`;
- `assets/gen/test`: 100 robots `gen-1-<i>` = `generate_set(100, seed=TEST_SEED, exclude_topologies=<train's>)`,
  so no test robot has the limb-tree shape (`topology_key`) of a train robot.
Both in MetaMorph format (xml/<id>.xml + metadata/<id>.json) via `save_set`. Every robot is checked against the
design space (`check_design_space`, `check_morphology`) and read back with `load_folder` before the script ends.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from mjx_morph.unimal.design_space import topology_key
from mjx_morph.unimal.draft import check_design_space
from mjx_morph.unimal.generator import generate_set
from mjx_morph.unimal.mjcf import save_set
from mjx_morph.unimal.reader import load_folder
from mjx_morph.unimal.validate import check_morphology

TRAIN_SEED = 0
TEST_SEED = 1
NUM = 100
ROOT = Path(__file__).resolve().parents[1]


def _write(robots, folder: Path) -> None:
    for sub, ext in (("xml", "xml"), ("metadata", "json")):
        if (folder / sub).is_dir():
            for f in (folder / sub).glob(f"*.{ext}"):
                f.unlink()
    save_set(robots, folder)
    back = {m.name: m for m in load_folder(folder)}
    if set(back) != {m.name for m in robots}:
        raise SystemExit(f"{folder}: read back {len(back)} robots, wrote {len(robots)}")
    for m in robots:
        if back[m.name] != m:
            raise SystemExit(f"{folder}: {m.name} does not read back identically")


def _summary(label: str, robots) -> str:
    a = np.array([(m.num_limbs, m.dof, m.tree_depth, m.height, m.total_mass) for m in robots], dtype=float)
    cols = ("limbs", "dof", "depth", "height", "mass")
    parts = [f"{c} {a[:, i].min():g}-{a[:, i].max():g} (mean {a[:, i].mean():.2f})" for i, c in enumerate(cols)]
    topo = len({topology_key(m) for m in robots})
    return f"{label}: {len(robots)} robots, {topo} topologies; " + ", ".join(parts)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "assets" / "gen")
    args = ap.parse_args(argv)
    t0 = time.time()
    train = generate_set(NUM, TRAIN_SEED)
    t1 = time.time()
    test = generate_set(NUM, TEST_SEED, exclude_topologies={topology_key(m) for m in train})
    t2 = time.time()
    for m in train + test:
        problems = check_design_space(m) + check_morphology(m)
        if problems:
            raise SystemExit("\n".join(problems))
    assert not {topology_key(m) for m in train} & {topology_key(m) for m in test}
    _write(train, args.out / "train")
    _write(test, args.out / "test")
    print(_summary("gen/train", train) + f"; generated in {t1 - t0:.1f} s")
    print(_summary("gen/test", test) + f"; generated in {t2 - t1:.1f} s")
    print(f"wrote {args.out}/train and {args.out}/test")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
