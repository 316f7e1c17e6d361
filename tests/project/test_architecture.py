"""The package layers: every import (including those inside functions) points down or sideways
within a layer, never up (docs/architecture.md draws the map)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[2] / "src" / "hsicam"

# Lowest first. A module may import from its own layer or any layer below it.
LAYERS: list[set[str]] = [
    {"errors", "io", "memory", "devices", "progress", "spectral", "config", "resources", "configs", "version"},
    {"optics", "sensor", "color", "metrics"},
    {"cameras"},
    {"models"},
    {"solvers"},
    {"runs"},
    {"data"},
    {"report"},
    {"export"},
    {"engine"},
    {"cli", "__main__", "__init__"},
]
LAYER_OF = {name: i for i, names in enumerate(LAYERS) for name in names}


def _top(module: str) -> str:
    """hsicam.engine.train -> engine; hsicam -> __init__."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _imports(path: Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 and node.module.split(".")[0] == "hsicam":
            out.append((node.lineno, node.module))
            if node.module == "hsicam":
                out += [(node.lineno, f"hsicam.{a.name}") for a in node.names]
        elif isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names if a.name.split(".")[0] == "hsicam"]
    return out


MODULES = sorted(p for p in SRC.rglob("*.py"))


def test_every_package_has_a_layer():
    tops = {p.relative_to(SRC).parts[0].removesuffix(".py") for p in MODULES}
    assert tops <= set(LAYER_OF), f"add {sorted(tops - set(LAYER_OF))} to LAYERS and docs/architecture.md"


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(SRC)))
def test_imports_point_down(path):
    src_top = path.relative_to(SRC).parts[0].removesuffix(".py")
    upward = [f"line {ln}: {mod}" for ln, mod in _imports(path)
              if _top(mod) in LAYER_OF and LAYER_OF[_top(mod)] > LAYER_OF[src_top]]
    assert not upward, f"{path.relative_to(SRC)} ({src_top}, layer {LAYER_OF[src_top]}) imports upward: {upward}"
