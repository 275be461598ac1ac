"""The report built from two real tiny runs (rmomo and metamorph smoke runs, evaluated on short episodes by the
shared `evaluated_runs` fixture): every figure of the data they have is drawn and linked from report.md."""
from __future__ import annotations

import re

import jax

from mjx_morph.eval.report import build_report


def test_report_builds_from_two_tiny_runs(evaluated_runs, tmp_path):
    rmomo, metamorph = evaluated_runs
    md = build_report([rmomo, metamorph], tmp_path / "report", compare=["rmomo", "metamorph"])
    text = md.read_text()
    expected = ["learning_curve_ft.png", "returns_ft.png", "robot_diff_ft.png", "reward_per_step_ft.png"]
    for name in expected:
        png = tmp_path / "report" / name
        assert png.exists() and png.stat().st_size > 5000, name
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    linked = set(re.findall(r"\(([^)]+\.png)\)", text))
    drawn = {p.name for p in (tmp_path / "report").glob("*.png")}
    assert set(expected) <= drawn and drawn <= {l.split("/")[-1] for l in linked}
    assert "rmomo" in text and "metamorph" in text
    assert "### Parameters" in text and re.search(r"/ 100 ?M steps", text)    # parameter and wall-clock tables
    assert f"| {jax.devices()[0].device_kind} |" in text       # the runs' device, from devices.yaml
