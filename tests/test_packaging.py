"""Packaging: every third-party module that the package imports is declared in pyproject.toml."""

from __future__ import annotations

import ast
import re
import sys
from importlib.metadata import packages_distributions
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "hsicam"

tomllib = pytest.importorskip("tomllib") if sys.version_info >= (3, 11) else pytest.importorskip("tomli")


def _imported_top_level_modules() -> dict[str, str]:
    """{top-level module: first file importing it} over src/hsicam, imports inside functions included."""
    found: dict[str, str] = {}
    for f in sorted(SRC.rglob("*.py")):
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"), filename=str(f))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for n in names:
                found.setdefault(n.split(".")[0], str(f.relative_to(ROOT)))
    return found


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def test_every_third_party_import_is_declared():
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    declared = {_norm(re.split(r"[ <>=!~;\[]", r, maxsplit=1)[0])
                for r in [*meta["dependencies"], *(x for extra in meta["optional-dependencies"].values() for x in extra)]}
    dists = packages_distributions()
    missing = []
    for module, where in _imported_top_level_modules().items():
        if module == "hsicam" or module in sys.stdlib_module_names:
            continue
        candidates = {_norm(d) for d in dists.get(module, [module])}
        if not candidates & declared:
            missing.append(f"{module} (distribution {sorted(candidates)}, imported in {where})")
    assert not missing, "imported but not declared in pyproject.toml: " + "; ".join(missing)


def test_build_backend_supports_the_license_string():
    data = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    if isinstance(data["project"].get("license"), str):  # PEP 639 SPDX expression: setuptools >= 77
        (req,) = [r for r in data["build-system"]["requires"] if r.startswith("setuptools")]
        m = re.search(r">=\s*(\d+)", req)
        assert m and int(m.group(1)) >= 77, req
