"""How many self-collision pairs the cut keeps, against how many touch in a dense random sample.

    python -m experiments.self_pairs unimal100/train
    python -m experiments.self_pairs gen/train samples=3000 margin=0.01 slack=0.1

For one robot set: the slot pairs MJX checks with self-collision on and no cut (candidates), those whose two slots
some robot uses, those the cut keeps (mjx_morph/sim/selfcontact.py) and, of these, those the search showed to touch
(a pose found; a lower bound on the pairs that can touch), and those whose geoms come within the margin in `samples`
uniform random poses per robot posed by MuJoCo C (a weaker lower bound), in the joint ranges and in the ranges
widened by the slack; the same per robot (mean geom pairs); MJX's pairs and contacts of one padded robot on the
floor without and with the cut; the time the cut took. A touched pair that the cut does not keep would be a bug:
the command then exits with status 1.
"""
from __future__ import annotations

import dataclasses
import os
import sys
import time

from omegaconf import MISSING

import mujoco
from mjx_morph.run import register
from mjx_morph.sim import fidelity, padding, selfcontact
from mjx_morph.sim.padding import SolverOptions
from mjx_morph.sim.supertree import build_shared_tree
from mjx_morph.unimal.sets import load_set

from . import cli


@dataclasses.dataclass
class SelfPairsConfig:
    set: str = MISSING                 # robot set name or path
    samples: int = 3000                # random poses per robot for the lower bound
    margin: float = selfcontact.MARGIN
    slack: float = selfcontact.SLACK
    budget: int = selfcontact.BOX_BUDGET
    seed: int = 0


register("self_pairs_schema", SelfPairsConfig)


def measure(a: SelfPairsConfig) -> None:
    rs = load_set(a.set).robots
    tree = build_shared_tree(rs)
    n = len(rs)
    # a check of the search and its time: searched here, not read from the searches kept on disk
    os.environ[selfcontact.PAIR_CACHE_ENV] = ""
    cut = selfcontact.find_slot_pairs(rs, tree, a.margin, a.slack, a.budget)      # cold: nothing cached yet
    per_robot = [selfcontact.robot_pairs(m, a.margin, a.slack, a.budget) for m in rs]
    touched = {}
    for name, slack in (("ranges", 0.0), ("ranges+slack", a.slack)):
        node_pairs = [selfcontact.sampled_touching_pairs(m, a.samples, a.margin, a.seed, slack) for m in rs]
        touched[name] = (node_pairs, {selfcontact.slot_pair(tree, r, *p) for r, ps in enumerate(node_pairs)
                                      for p in ps})
    world = fidelity.FLOOR_WORLD
    mjx = {}
    for name, opts in (("no cut", SolverOptions(self_collision=True, self_collision_cut=False)),
                       ("cut", SolverOptions(self_collision=True, self_pairs=cut.kept))):
        mm = mujoco.MjModel.from_xml_string(padding.padded_mjcf(rs[0], tree, 0, world, opts))
        mjx[name] = (selfcontact.mjx_pair_counts(mm), selfcontact.mjx_contact_count(mm))
    print(f"# {a.set}: {n} robots, shared tree of {tree.num_slots} bodies; margin {a.margin} m, slack {a.slack} rad, "
          f"budget {a.budget} boxes per pair, {a.samples} samples per robot")
    print(f"slot pairs: {len(selfcontact.candidate_slot_pairs(tree))} candidates without a cut, "
          f"{len(selfcontact.used_slot_pairs(rs, tree))} used by some robot, {len(cut.kept)} kept by the cut "
          f"({len(cut.touching)} shown to touch), "
          + ", ".join(f"{len(s)} touched in the sample ({k})" for k, (_, s) in touched.items()))
    mean = lambda xs: sum(xs) / n
    print(f"per robot (geom pairs, mean): {mean([len(p.candidates) for p in per_robot]):.1f} candidates, "
          f"{mean([len(p.kept) for p in per_robot]):.2f} kept ({mean([len(p.touching) for p in per_robot]):.2f} "
          f"shown to touch, {mean([len(p.unresolved) for p in per_robot]):.2f} unproved within the budget), "
          + ", ".join(f"{mean([len(x) for x in ps]):.2f} touched in the sample ({k})" for k, (ps, _) in touched.items()))
    for name, (pairs, contacts) in mjx.items():
        print(f"MJX, {name}: " + ", ".join(f"{k} {v}" for k, v in pairs.items()) + f"; {contacts} contacts per env")
    print(f"cut computed in {cut.seconds:.1f} s ({sum(p.boxes for p in per_robot)} poses evaluated, "
          f"{cut.unresolved} robot pairs unproved)")
    missed = [(rs[r].name, p) for r, p_r in enumerate(per_robot)
              for p in touched["ranges+slack"][0][r] if p not in p_r.kept]
    if missed:
        print(f"ERROR: {len(missed)} touched pairs not kept, e.g. {missed[:5]}")
        raise SystemExit(1)


def main(argv=None) -> int:
    return cli.main(measure, "self_pairs_schema", SelfPairsConfig, __doc__, argv, positional="set")


if __name__ == "__main__":
    sys.exit(main())
