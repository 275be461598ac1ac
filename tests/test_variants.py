"""Dynamics/kinematics variants (count, names, one change type each, determinism) and the shipped generated sets."""
from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import pytest

from mjx_morph.unimal import variants as V
from mjx_morph.unimal.design_space import DENSITIES, GEARS, JOINT_RANGES, topology_key
from mjx_morph.unimal.draft import check_design_space
from mjx_morph.unimal.generator import generate_set
from mjx_morph.unimal.morphology import Morphology
from mjx_morph.unimal.reader import load_folder
from mjx_morph.unimal.validate import check_morphology

ROOT = Path(__file__).resolve().parents[1]
GEN = ROOT / "assets" / "gen"


def _base_folder() -> Path | None:
    """The original train robots when present, else the shipped gen/train."""
    orig = Path(os.environ.get("MJX_MORPH_UNIMALS", ROOT.parent / "shared" / "unimals_100")) / "train"
    if (orig / "xml").is_dir():
        return orig
    return GEN / "train" if (GEN / "train" / "xml").is_dir() else None


@pytest.fixture(scope="module")
def base() -> list[Morphology]:
    folder = _base_folder()
    if folder is None:
        pytest.skip("no robots: neither ../shared/unimals_100/train nor assets/gen/train exists "
                    "(run python -m experiments.make_assets)")
    return load_folder(folder)


@pytest.fixture(scope="module")
def variants(base) -> list[Morphology]:
    return V.make_variants(base)


@pytest.fixture(scope="module")
def gen_train() -> list[Morphology]:
    if not (GEN / "train" / "xml").is_dir():
        pytest.skip("assets/gen/train missing: run python -m experiments.make_assets")
    return load_folder(GEN / "train")


# ---- count and names ------------------------------------------------------------------------------------------
def test_count_and_names(base, variants):
    assert len(variants) == len(base) * len(V.CHANGE_TYPES) * 4
    if len(base) == 100:
        assert len(variants) == 2400
    names = [v.name for v in variants]
    assert len(set(names)) == len(names)
    it = iter(variants)
    for m in base:
        for change in V.CHANGE_TYPES:
            for k in range(4):
                v = next(it)
                assert v.name == f"{m.name}_{change}_{k}"
                assert V.variant_change(v.name) == (m.name, change, k)


def test_variant_change_parser():
    assert V.variant_change("floor-5506-10-6-01-15-48-35_damping_3") == ("floor-5506-10-6-01-15-48-35", "damping", 3)
    assert V.variant_change("mvt-5506-12-6-17-12-20-06_limb_params_3") == ("mvt-5506-12-6-17-12-20-06", "limb_params", 3)
    assert V.variant_change("gen-0-7_joint_angle_0") == ("gen-0-7", "joint_angle", 0)
    for bad in ("floor-1409-0-3-01-15-56-55", "x_friction_1", "x_gear_", "_gear_1"):
        with pytest.raises(ValueError):
            V.variant_change(bad)


# ---- each variant changes only its change type ----------------------------------------------------------------
_JOINT_FIELD = {"armature": "armature", "damping": "damping", "gear": "gear", "joint_angle": "range"}


def _changed_only(b: Morphology, v: Morphology, change: str) -> None:
    where = v.name
    assert v != dataclasses.replace(b, name=v.name), f"{where}: nothing changed"
    assert v.mirror_pairs == b.mirror_pairs and v.torso_radius == b.torso_radius, where
    assert [(l.id, l.parent, l.radius) for l in v.limbs] == [(l.id, l.parent, l.radius) for l in b.limbs], where
    if change != "density":
        assert v.torso_density == b.torso_density and [l.density for l in v.limbs] == [l.density for l in b.limbs]
    else:
        assert v.torso_density != b.torso_density and v.limbs[0].density != b.limbs[0].density, where
        assert len({l.density for l in v.limbs}) == 1, where
    if change != "limb_params":
        assert v.height == b.height, where
        assert [(l.pos, l.tip) for l in v.limbs] == [(l.pos, l.tip) for l in b.limbs], where
    else:
        tip_changed = {l.id for l, k in zip(v.limbs, b.limbs) if l.tip != k.tip}
        pos_changed = {i for i, (l, k) in enumerate(zip(v.limbs, b.limbs)) if l.pos != k.pos}
        groups = [set(p) for p in b.mirror_pairs] + [{l.id} for l in b.limbs]
        assert tip_changed in groups, f"{where}: capsules of {tip_changed} changed; expected one limb group"
        for i in pos_changed:
            assert b.limbs[b.limbs[i].parent].id in tip_changed, f"{where}: limb {b.limbs[i].id} moved"
    for lv, lb in zip(v.limbs, b.limbs):
        assert [j.kind for j in lv.joints] == [j.kind for j in lb.joints], where
        for jv, jb in zip(lv.joints, lb.joints):
            for f in ("pos", "axis", "stiffness", "range", "gear", "armature", "damping"):
                if _JOINT_FIELD.get(change) != f:
                    assert getattr(jv, f) == getattr(jb, f), f"{where}: limb{jv.kind}/{lv.id} {f} changed"
    if change in ("armature", "damping"):
        values = {getattr(j, change) for _, j in v.joints()}
        assert len(values) == 1, where
        value = values.pop()
        assert V.JOINT_PARAM_RANGE[0] <= value <= V.JOINT_PARAM_RANGE[1], where
        assert not V.JOINT_PARAM_EXCLUDE[0] <= value <= V.JOINT_PARAM_EXCLUDE[1], where


def test_each_variant_changes_only_its_type(base, variants):
    by_name = {m.name: m for m in base}
    for v in variants:
        b_id, change, _ = V.variant_change(v.name)
        _changed_only(by_name[b_id], v, change)


def test_variants_stay_in_design_space(base, variants):
    by_name = {m.name: m for m in base}
    for v in variants:
        b_id, change, _ = V.variant_change(v.name)
        assert check_morphology(v) == [], v.name
        for _, j in v.joints():
            assert tuple(j.range) in JOINT_RANGES and j.gear in GEARS, v.name
        assert v.torso_density in DENSITIES and v.limbs[0].density in DENSITIES, v.name
        if change == "limb_params":
            # geometry, symmetry, no new self-contact (originals may carry one), standing height by our rule
            base_problems = {p.replace(b_id, "*") for p in check_design_space(by_name[b_id], height=False)}
            problems = {p.replace(v.name, "*") for p in check_design_space(v)}
            assert problems <= base_problems, v.name
            assert all(l.length - 0.05 == pytest.approx(round(l.length - 0.05, 1), abs=0.01) for l in v.limbs)


def test_variants_of_generated_robots_pass_every_check(gen_train):
    for v in V.make_variants(gen_train[:3]):
        change = V.variant_change(v.name)[1]
        assert check_design_space(v, dynamics=change not in ("armature", "damping")) == [], v.name


def test_variants_are_deterministic(base, variants):
    again = V.make_variants(base[:2])
    assert again == variants[:48]
    other = V.make_variants(base[:2], seed=1)
    assert other != again
    assert [v.name for v in other] == [v.name for v in again]
    one = V.make_variants(base[:1], types=("gear",))
    assert one == [v for v in variants[:24] if "_gear_" in v.name]
    # the four variants of one robot and change type are distinct
    for i in range(0, len(variants), 4):
        group = [dataclasses.replace(v, name="x") for v in variants[i:i + 4]]
        assert len({repr(v) for v in group}) == 4


def test_stable_hash():
    # fixed values: the seeds must not depend on the process (Python's hash() of a str is salted per process)
    assert V.stable_hash("gen-0-0") == 709196191304722535
    assert V.stable_hash("damping") == 6670091603695006716


# ---- the shipped generated sets -------------------------------------------------------------------------------
def test_shipped_sets_load_and_are_disjoint(gen_train):
    if not (GEN / "test" / "xml").is_dir():
        pytest.skip("assets/gen/test missing: run python -m experiments.make_assets")
    test = load_folder(GEN / "test")
    assert len(gen_train) == 100 and len(test) == 100
    assert {m.name for m in gen_train} == {f"gen-0-{i}" for i in range(100)}
    assert {m.name for m in test} == {f"gen-1-{i}" for i in range(100)}
    train_keys = {topology_key(m) for m in gen_train}
    assert not train_keys & {topology_key(m) for m in test}
    for m in gen_train + test:
        assert check_morphology(m) == [], m.name
        assert check_design_space(m) == [], m.name


def test_shipped_sets_match_the_generator(gen_train):
    """The files are what `python -m experiments.make_assets` makes with the current code."""
    by_name = {m.name: m for m in gen_train}
    for m in generate_set(2, seed=0):
        assert by_name[m.name] == m
