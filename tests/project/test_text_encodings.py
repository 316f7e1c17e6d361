"""Every text file hsicam reads or writes names its encoding.

Without ``encoding=``, Python opens text in the locale's encoding: UTF-8 on Linux and macOS, but the ANSI code page
(cp1252 …) on Windows before Python 3.15, so a file written on one machine and read on another, or a non-ASCII
character in a path recorded in a run, reads differently there. Ten places in src/hsicam (the run's config.yaml and
prior.yaml, a checkpoint's state.json, metrics.jsonl for the report and the experiments' finished check, a sensor
image's sidecar) left it to the locale until session 62, and two outside it (benchmarks/bench_capture.py,
examples/train_tiny.py). Binary opens, and calls that pass ``**kwargs`` on, are
exempt."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).parents[2]
#: the package and the scripts, benchmarks and examples that ship beside it (a user runs them on Windows too)
CODE = [ROOT / "src" / "hsicam", ROOT / "scripts", ROOT / "benchmarks", ROOT / "examples"]
TEXT_CALLS = {"open", "read_text", "write_text", "atomic_open"}
NOT_FILE_OPENERS = {"os", "Image", "h5py", "tarfile", "zipfile", "gzip"}


def _mode(call: ast.Call) -> str | None:
    for k in call.keywords:
        if k.arg == "mode":
            return k.value.value if isinstance(k.value, ast.Constant) else "?"
    if len(call.args) > 1 and isinstance(call.args[1], ast.Constant):
        return call.args[1].value
    return None


def text_opens_without_encoding(tree: ast.AST) -> list[int]:
    """Line numbers of the calls in ``tree`` that open, read or write text without ``encoding=``."""
    lines = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        func = node.func
        name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
        if name not in TEXT_CALLS:
            continue
        if isinstance(func, ast.Attribute) and getattr(func.value, "id", "") in NOT_FILE_OPENERS:
            continue
        keywords = {k.arg for k in node.keywords}
        if "encoding" in keywords or None in keywords:  # named, or passed on by **kwargs
            continue
        if name in ("open", "atomic_open") and "b" in (_mode(node) or ""):
            continue
        lines.append(node.lineno)
    return lines


def test_the_check_finds_a_text_open_without_encoding():
    code = ("open(p)\nopen(p, 'rb')\np.read_text()\np.read_text(encoding='utf-8')\natomic_open(p)\n"
            "atomic_open(p, 'wb')\nos.open(p, 0)\np.write_text(t, **kw)\nopen(p, mode='w')\n")
    assert text_opens_without_encoding(ast.parse(code)) == [1, 3, 5, 9]


def test_every_text_file_hsicam_opens_names_its_encoding():
    found = [f"{path.relative_to(ROOT)}:{line}"
             for path in sorted(p for folder in CODE for p in folder.rglob("*.py"))
             for line in text_opens_without_encoding(ast.parse(path.read_text(encoding="utf-8")))]
    assert found == [], "text opened in the locale's encoding (add encoding='utf-8'): " + ", ".join(found)
