"""Packaging: every third-party module that the package imports is declared in pyproject.toml; hsicam as an installed
package (``pip install hsicam``, ``pip install 'hsicam[synth]'``): the files it reads at run time ship in the wheel, and
a missing or outdated optional package is one line naming its extra."""

from __future__ import annotations

import ast
import os
import re
import shutil
import subprocess
import sys
import zipfile
from importlib.metadata import packages_distributions
from pathlib import Path

import pytest
from cli_helpers import run_cli_in_process

ROOT = Path(__file__).resolve().parents[2]
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


def test_the_built_version_is_the_packages_own_version(tmp_path):
    """One home for the version: setuptools (the build backend's own reader) takes the wheel's Version from
    src/hsicam/version.py's ``__version__``, so bumping that one line bumps ``hsicam --version``, the records and the
    installed metadata alike (a static ``[project] version`` was a second copy nothing tied: session 76's hunt)."""
    config = pytest.importorskip("setuptools.config.pyprojecttoml")
    import hsicam

    assert config.read_configuration(ROOT / "pyproject.toml", expand=True)["project"]["version"] == hsicam.__version__
    (tmp_path / "src" / "hsicam").mkdir(parents=True)
    shutil.copy2(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    shutil.copy2(SRC / "__init__.py", tmp_path / "src" / "hsicam" / "__init__.py")
    home = (SRC / "version.py").read_text(encoding="utf-8")
    bumped, n = re.subn(r'(?m)^__version__ = "[^"]*"$', '__version__ = "7.5.3"', home)
    assert n == 1
    (tmp_path / "src" / "hsicam" / "version.py").write_text(bumped, encoding="utf-8")
    assert config.read_configuration(tmp_path / "pyproject.toml", expand=True)["project"]["version"] == "7.5.3"


def test_the_mit_license_text_ships_beside_its_expression():
    """``License-Expression: MIT`` came with no license text (session 76's hunt): LICENSE holds the MIT terms, and
    ``license-files`` names it (the wheel's .dist-info/licenses/ and the sdist carry it: the slow tests build both)."""
    project = _pyproject()["project"]
    assert project["license"] == "MIT"
    assert project["license-files"] == ["LICENSE"]
    text = (ROOT / "LICENSE").read_text(encoding="utf-8")
    assert text.startswith("MIT License\n\nCopyright (c) ") and "the hsicam developers" in text.splitlines()[2]
    assert "Permission is hereby granted, free of charge, to any person obtaining a copy" in text
    assert 'THE SOFTWARE IS PROVIDED "AS IS", WITHOUT WARRANTY OF ANY KIND' in text


# ---- what the wheel ships ---------------------------------------------------------------------------------
def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))


def _resource_files() -> set[str]:
    """Every non-Python file under src/hsicam (the configs/ symlink followed, as setuptools does), relative."""
    out = set()
    for d, dirs, files in os.walk(SRC, followlinks=True):
        dirs[:] = [x for x in dirs if x != "__pycache__" and not x.startswith(".")]
        for f in files:
            if not f.endswith((".py", ".pyc")) and not f.startswith("."):
                out.add((Path(d) / f).relative_to(SRC).as_posix())
    return out


def _package_data_matches(package: Path = SRC) -> set[str]:
    """The files under the package folder ``package`` that pyproject.toml's package-data globs ship, relative."""
    globs = _pyproject()["tool"]["setuptools"]["package-data"]["hsicam"]
    return {p.relative_to(package).as_posix() for g in globs for p in package.glob(g) if p.is_file()}


def _loaded_at_run_time() -> set[str]:
    """The files the code reads: the presets, the CIE table of hsicam.color, each shipped camera's files."""
    from hsicam.config import PRESETS_DIR, preset_names
    from hsicam.runs import pretrained

    names = {f"configs/{n}.yaml" for n in preset_names()}
    assert PRESETS_DIR == SRC / "configs" or PRESETS_DIR.resolve() == (SRC / "configs").resolve()
    names.add("resources/cie1931_2deg_d65.csv")
    shipped = pretrained.package_root()
    for cam in pretrained.camera_folders(shipped):
        names |= {p.resolve().relative_to(SRC.resolve()).as_posix() for p in (shipped / cam).iterdir() if p.is_file()}
    return names


def test_every_resource_file_is_matched_by_package_data():
    files = _resource_files()
    loaded = _loaded_at_run_time()
    # what the code loads exists in the tree (a checkout without symlinks has no presets: src/hsicam/configs
    # is then a text file, and `--config tiny` would find nothing)
    assert {"configs/tiny.yaml", "configs/quick.yaml", "resources/cie1931_2deg_d65.csv",
            "resources/pretrained/standard/model.safetensors"} <= loaded
    assert loaded <= files, sorted(loaded - files)
    unmatched = files - _package_data_matches()
    assert not unmatched, f"add a [tool.setuptools.package-data] glob for {sorted(unmatched)}"


def test_package_data_ships_every_file_a_packed_camera_may_hold(tmp_path, cache_env):
    """A camera built from a material table carries a copy of it (camera.doe.material.csv; a coded aperture's is a
    .npy), which the package-data globs (.safetensors, .yaml, .md, .json) left out of the wheel: installed, the
    camera was listed as usable and failed at `--run pretrained:NAME` (session 76's packaging hunt). A camera packed
    from a run trained on a table into a package-shaped folder: every file pack writes is one a camera may hold
    (hsicam.runs.pretrained.FILES) and shipped, and so is every name of FILES."""
    from hsicam.config import load_config
    from hsicam.engine.pretrained import pack_pretrained
    from hsicam.engine.train import train
    from hsicam.runs import pretrained
    from conftest import TINY_CAMERA_OVERRIDES

    table = tmp_path / "pmma.csv"
    table.write_text("wavelength_nm,n\n400,1.50\n700,1.48\n")
    train(load_config("tiny", [*TINY_CAMERA_OVERRIDES, "train.epochs=1", f"camera.doe.material={table}"]),
          tmp_path / "run", progress=False)
    package = tmp_path / "hsicam"
    cam = pack_pretrained(tmp_path / "run", "tbl", package / "resources" / "pretrained")
    written = {p.name for p in cam.iterdir() if not p.name.startswith(".")}  # its .complete marker is not read
    assert {"camera.doe.material.csv", "camera_files.json", "config.yaml", "model.safetensors"} <= written
    assert written <= set(pretrained.FILES)
    every = package / "resources" / "pretrained" / "every"
    every.mkdir()
    for name in pretrained.FILES:
        (every / name).write_bytes(b"")
    shipped = _package_data_matches(package)
    assert not {f"resources/pretrained/tbl/{n}" for n in written} - shipped
    assert not {f"resources/pretrained/every/{n}" for n in pretrained.FILES} - shipped


def _local_setuptools_major() -> int:
    """The major version of the setuptools this interpreter has (0: none)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return int(version("setuptools").split(".")[0])
    except (PackageNotFoundError, ValueError):
        return 0


def _build_tree(tmp_path: Path) -> Path:
    """A copy of what a build reads, so that an in-tree build leaves no build/ or egg-info in the checkout."""
    src = tmp_path / "src_tree"
    src.mkdir()
    for f in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(ROOT / f, src / f)
    shutil.copytree(ROOT / "src", src / "src", symlinks=False,
                    ignore=shutil.ignore_patterns("__pycache__", "*.egg-info", "*.pyc"))
    return src


@pytest.mark.slow
def test_built_wheel_holds_the_configs_cameras_and_resources(tmp_path):
    src = _build_tree(tmp_path)
    wheel_cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path / "dist"), str(src)]
    run = subprocess.run(wheel_cmd, capture_output=True, text=True, timeout=600)
    if run.returncode != 0 and re.search(r"(No matching distribution found for setuptools|Could not find a version "
                                         r"that satisfies the requirement setuptools|NewConnectionError|"
                                         r"Temporary failure in name resolution)", run.stderr):
        if _local_setuptools_major() < 77:  # no index, and no backend here that reads the license string
            pytest.skip(f"pip cannot reach an index for the build backend: {run.stderr.strip().splitlines()[-1]}")
        run = subprocess.run([*wheel_cmd, "--no-build-isolation", "--no-index"], capture_output=True, text=True,
                             timeout=600)
    assert run.returncode == 0, run.stderr
    (wheel,) = (tmp_path / "dist").glob("hsicam-*.whl")
    import hsicam

    assert wheel.name.startswith(f"hsicam-{hsicam.__version__}-")
    archive = zipfile.ZipFile(wheel)
    names = set(archive.namelist())
    metadata = archive.read(f"hsicam-{hsicam.__version__}.dist-info/METADATA").decode()
    assert f"\nVersion: {hsicam.__version__}\n" in metadata
    assert "\nLicense-Expression: MIT\n" in metadata and "\nLicense-File: LICENSE\n" in metadata
    licence = archive.read(f"hsicam-{hsicam.__version__}.dist-info/licenses/LICENSE")
    assert licence == (ROOT / "LICENSE").read_bytes()
    want = {f"hsicam/{f}" for f in _resource_files()}
    assert want <= names, sorted(want - names)
    assert {f"hsicam/{f}" for f in _loaded_at_run_time()} <= names
    assert "hsicam/cli/__init__.py" in names and "hsicam/runs/pretrained.py" in names


@pytest.mark.slow
def test_built_sdist_holds_the_license_and_the_packages_version(tmp_path):
    """The sdist (setuptools' own build_sdist, with the setuptools here) carries LICENSE and names the version of
    src/hsicam/__init__.py."""
    import tarfile

    import hsicam

    if _local_setuptools_major() < 77:
        pytest.skip("the setuptools here predates the license string (PEP 639) of pyproject.toml")
    src = _build_tree(tmp_path)
    run = subprocess.run([sys.executable, "-c", "from setuptools import build_meta as b; print(b.build_sdist('dist'))"],
                         cwd=src, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    name = f"hsicam-{hsicam.__version__}"
    assert run.stdout.split()[-1] == f"{name}.tar.gz"
    with tarfile.open(src / "dist" / f"{name}.tar.gz") as tar:
        assert tar.extractfile(f"{name}/LICENSE").read() == (ROOT / "LICENSE").read_bytes()
        info = tar.extractfile(f"{name}/PKG-INFO").read().decode()
    assert f"\nVersion: {hsicam.__version__}\n" in info and "\nLicense-File: LICENSE\n" in info


# ---- optional packages: one line naming the extra --------------------------------------------------------
# gdstk: test_export.py::test_export_without_gdstk; OpenEXR's reader: test_readers_rare_paths.py (function level).

def _one_error_line(res) -> str:
    lines = [x for x in res.stderr.splitlines() if x.startswith("hsicam: error:")]
    assert res.returncode == 2 and len(lines) == 1 and "Traceback" not in res.stderr, res.stderr
    return lines[0]


def test_synthetic_data_without_colour_science_is_one_line_naming_the_synth_extra(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "colour", None)  # `import colour`: ImportError
    # bands no other test builds the library for (its lru_cache would skip the import)
    res = run_cli_in_process("data", "synth", "--n", "1", "--size", "32", "--seed", "3", "--out", str(tmp_path / "s"),
                             "--set", "bands.start_nm=425", "--set", "bands.stop_nm=705", "--set", "bands.step_nm=70",
                             env={"HSICAM_CACHE": str(tmp_path / "cache")})
    assert _one_error_line(res) == ("hsicam: error: generating the synthetic dataset needs colour-science "
                                    "(pip install 'hsicam[synth]'): import of colour halted; None in sys.modules")
    assert not (tmp_path / "s").exists()


def test_colour_science_older_than_the_datasets_read_is_one_line_naming_the_upgrade(tmp_path, monkeypatch):
    """colour-science 0.4.4-0.4.6 (which the synth extra used to allow) stop the generator with a KeyError ('PMC')
    or an AttributeError (SDS_TCS of one set): a traceback. Now one line naming the version needed."""
    colour = pytest.importorskip("colour")
    monkeypatch.setattr(colour, "__version__", "0.4.6")
    res = run_cli_in_process("data", "synth", "--n", "1", "--size", "32", "--seed", "3", "--out", str(tmp_path / "s"),
                             "--set", "bands.start_nm=425", "--set", "bands.stop_nm=705", "--set", "bands.step_nm=35",
                             env={"HSICAM_CACHE": str(tmp_path / "cache")})
    assert _one_error_line(res) == ("hsicam: error: generating the synthetic dataset needs colour-science >= 0.4.7, "
                                    "found 0.4.6 (pip install -U 'hsicam[synth]')")


def test_synth_and_dev_extras_ask_for_the_colour_science_the_code_needs():
    from hsicam.data.spectral_sources import COLOUR_MIN_VERSION

    need = "colour-science>=" + ".".join(map(str, COLOUR_MIN_VERSION))
    extras = _pyproject()["project"]["optional-dependencies"]
    assert extras["synth"] == [need]
    assert [d for d in extras["dev"] if d.startswith("colour-science")] == [need]


def test_reading_an_exr_scene_without_openexr_is_one_line_naming_the_exr_extra(tmp_path, monkeypatch):
    p = tmp_path / "scene.exr"
    p.write_bytes(b"\x76\x2f\x31\x01")  # the OpenEXR magic number
    monkeypatch.setitem(sys.modules, "OpenEXR", None)
    res = run_cli_in_process("simulate", "--config", "tiny", "--scene", str(p), "--out", str(tmp_path / "sim"))
    assert _one_error_line(res) == (f"hsicam: error: {p}: reading OpenEXR needs the 'openexr' package "
                                    "(pip install 'hsicam[exr]')")


def test_data_sources_without_colour_science_lists_the_registry_and_says_why_the_counts_are_unknown(monkeypatch, capsys):
    """`hsicam data sources` without colour-science printed '?' in every count and said nothing about why (every
    exception swallowed, a bug's included). Now the registry as before on stdout, and one line on stderr naming the
    extra."""
    from hsicam.cli import main
    from hsicam.data import spectral_sources

    monkeypatch.setitem(sys.modules, "colour", None)
    monkeypatch.setattr(spectral_sources, "_library_cached", spectral_sources._library_cached.__wrapped__)
    assert main(["data", "sources"]) == 0
    out, err = capsys.readouterr()
    rows = out.splitlines()
    assert [r.split()[0] for r in rows] == list(spectral_sources.SOURCES)
    assert all(r.split()[2] == "?" for r in rows)
    assert err.strip() == ("hsicam: counts '?': generating the synthetic dataset needs colour-science "
                           "(pip install 'hsicam[synth]'): import of colour halted; None in sys.modules")
