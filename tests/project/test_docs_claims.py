"""Claims of the user documentation tied to the code, so that they cannot go stale silently."""

from __future__ import annotations

import dataclasses
import importlib
import re
from pathlib import Path

import pytest
import yaml

from hsicam.config import MosaicConfig, UnrolledConfig

ROOT = Path(__file__).resolve().parents[2]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def _settings_table(text: str, heading: str) -> dict[str, str]:
    """The ``| setting | default | meaning |`` table under the ``## heading`` section: {key: default text}."""
    section = text.split(heading, 1)[1].split("\n## ", 1)[0]
    rows = re.findall(r"^\| `([a-z_]+)` \| ([^|]+) \|", section, flags=re.M)
    assert rows, f"no settings table under {heading!r}"
    return {key: value.strip() for key, value in rows}


@pytest.mark.parametrize("heading, cls", [("## `model.kind = mosaic`", MosaicConfig),
                                          ("## `model.kind = unrolled`", UnrolledConfig)])
def test_networks_md_settings_tables_match_the_config_defaults(heading, cls):
    """docs/networks.md's settings tables list every key of the section with the dataclass's default."""
    table = _settings_table((ROOT / "docs" / "networks.md").read_text(encoding="utf-8"), heading)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    assert set(table) == set(fields)
    for key, text in table.items():
        default = getattr(cls(), key)
        if dataclasses.is_dataclass(default):
            assert text == f"{type(default).__name__}()", key
        else:
            assert yaml.safe_load(text) == default, (key, text, default)


def _resolves(name: str) -> bool:
    parts = name.split(".")
    for n in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:n]))
        except ModuleNotFoundError:
            continue
        for attr in parts[n:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


def test_every_dotted_hsicam_name_in_the_docs_exists():
    """Every ``hsicam.module.name`` the README and docs/*.md cite can be imported (nothing moved or renamed)."""
    cited: dict[str, str] = {}
    for path in DOCS:
        for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            for m in re.finditer(r"\bhsicam(?:\.[A-Za-z_][A-Za-z_0-9]*)+", line):
                cited.setdefault(m.group(0), f"{path.name}:{i}")
    assert len(cited) > 20
    missing = {name: where for name, where in cited.items() if not _resolves(name)}
    assert not missing


def test_the_held_out_sources_the_docs_name_are_each_presets():
    """`hsicam demo --config tiny` held out nist-cqs while README.md said the demo holds out two sources and nothing
    said which preset holds out what: docs/usage.md names every preset's data.holdout_sources, README.md the demo's
    (quick's), each read here from the shipped config files."""
    from hsicam.config import load_config
    from hsicam.data.spectral_sources import parse_holdout

    usage = (ROOT / "docs" / "usage.md").read_text(encoding="utf-8")
    claim = usage.split("Held-out spectral sources (`data.holdout_sources`", 1)[1].split("\n\n", 1)[0]
    claim = claim.split("): ", 1)[1].split(" (", 1)[0].replace("\n", " ")
    said: dict[str, tuple[str, ...]] = {}
    for part in claim.split("; "):
        ids, presets = re.fullmatch(r"`([a-z0-9,-]+)` in (.+)", part).groups()
        for preset in re.findall(r"`([a-z_-]+)`", presets):
            said[preset] = tuple(ids.split(","))
    shipped = sorted(p.stem for p in (ROOT / "src" / "hsicam" / "configs").glob("*.yaml"))
    assert sorted(said) == shipped
    for preset, ids in said.items():
        assert parse_holdout(load_config(preset).data.holdout_sources) == parse_holdout(",".join(ids)), preset
    readme = (ROOT / "README.md").read_text(encoding="utf-8").split("## What `make demo` does", 1)[1].split("\n## ")[0]
    readme = " ".join(readme.split())
    demo = parse_holdout(load_config("quick").data.holdout_sources)
    assert "sources, " + " and ".join(f"`{s}`" for s in demo) + ", are held out" in readme
    assert f"the `tiny` preset holds out {', '.join(f'`{s}`' for s in said['tiny'])}," in readme
