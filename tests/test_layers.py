"""The stages' layering (docs/architecture.md): a module of mjx_morph imports only its own stage and the stages
below it; sim and nets, side by side, meet only in layout.py."""
from __future__ import annotations

import ast
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "mjx_morph"
# the stage of each top-level name in mjx_morph, and which stages each may import
STAGE = {"unimal": 0, "layout": 1, "sim": 2, "nets": 2, "ppo": 3, "run": 4, "eval": 5}


def _allowed(stage: str, target: str) -> bool:
    if target == stage:
        return True
    if STAGE[target] == STAGE[stage]:           # sim and nets: siblings
        return False
    return STAGE[target] < STAGE[stage]


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, top-level mjx_morph name) of every import of mjx_morph in `path`, relative ones resolved."""
    rel = path.relative_to(PACKAGE.parent).with_suffix("").parts          # ("mjx_morph", "sim", "env")
    package = rel[:-1]                      # an __init__.py's package is its folder, as a module's
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - node.level + 1]
                parts = list(base) + (node.module.split(".") if node.module else [])
                if len(parts) == 1:          # `from .. import x` at the package's top: the names are the modules
                    parts += [a.name for a in node.names][:1]
            else:
                parts = (node.module or "").split(".")
            if parts[0] == "mjx_morph" and len(parts) > 1:
                out.append((node.lineno, parts[1]))
        elif isinstance(node, ast.Import):
            for a in node.names:
                parts = a.name.split(".")
                if parts[0] == "mjx_morph" and len(parts) > 1:
                    out.append((node.lineno, parts[1]))
    return out


def test_imports_only_go_down():
    modules = sorted(PACKAGE.rglob("*.py"))
    assert len(modules) > 30, "the package was not found"
    seen, bad = set(), []
    for path in modules:
        parts = path.relative_to(PACKAGE).with_suffix("").parts
        stage = parts[0]
        if stage == "__init__":
            continue
        assert stage in STAGE, f"{path}: a new top-level module, give it a stage in tests/test_layers.py"
        for line, target in _imports(path):
            assert target in STAGE, f"{path}:{line}: imports mjx_morph.{target}, which has no stage"
            seen.add((stage, target))
            if not _allowed(stage, target):
                bad.append(f"{path.relative_to(PACKAGE.parent)}:{line}: {stage} imports {target}")
    assert not bad, "imports that go up or sideways:\n" + "\n".join(bad)
    # the check sees the real structure: these edges exist
    assert {("sim", "unimal"), ("ppo", "nets"), ("run", "ppo"), ("eval", "run")} <= seen, seen


def test_the_check_catches_an_import_that_goes_up(tmp_path, monkeypatch):
    """The resolver reads relative imports as Python does: `from ..ppo import x` in mjx_morph/sim/ is mjx_morph.ppo."""
    pkg = tmp_path / "mjx_morph"
    (pkg / "sim" / "terrain").mkdir(parents=True)
    f = pkg / "sim" / "terrain" / "grid.py"
    f.write_text("from ...ppo import loss\nfrom ..env import X\nfrom . import corridor\n")
    g = pkg / "sim" / "env.py"
    g.write_text("from .. import nets\nimport mjx_morph.run.loop\n")
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", pkg)
    assert _imports(f) == [(1, "ppo"), (2, "sim"), (3, "sim")]
    assert _imports(g) == [(1, "nets"), (2, "run")]
    assert not _allowed("sim", "ppo") and not _allowed("sim", "nets") and _allowed("ppo", "sim")
