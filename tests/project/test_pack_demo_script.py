"""scripts/pack_demo.sh packs a demo folder for the trip back from a lent GPU machine: without the run's
checkpoints, and in 15 MiB parts that rejoin into the archive when it is larger (the device tool brings back files
of at most 16 MiB; a paper-scale network's weights alone are 16 MiB)."""

from __future__ import annotations

import os
import subprocess
import tarfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "pack_demo.sh"


def _demo(tmp_path: Path, weights_bytes: int) -> Path:
    demo = tmp_path / "demo"
    (demo / "run" / "checkpoints").mkdir(parents=True)
    (demo / "results.json").write_text('{"mean": {"psnr": 40.0}}')
    (demo / "run" / "checkpoints" / "step_100.safetensors").write_bytes(b"x" * 1000)
    (demo / "run" / "model.safetensors").write_bytes(os.urandom(weights_bytes))  # incompressible, as weights are
    return demo


def test_a_small_demo_is_one_archive_without_checkpoints(tmp_path):
    out = tmp_path / "out" / "demo.tar.gz"
    out.parent.mkdir()
    run = subprocess.run(["bash", str(SCRIPT), str(_demo(tmp_path, 1000)), str(out)], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert [p.name for p in out.parent.iterdir()] == ["demo.tar.gz"]
    with tarfile.open(out) as tar:
        names = set(tar.getnames())
    assert {"./results.json", "./run/model.safetensors"} <= names
    assert not any("checkpoints" in n for n in names)


def test_a_large_demo_comes_in_15_mib_parts_that_rejoin(tmp_path):
    demo = _demo(tmp_path, 20 * 2**20)
    out = tmp_path / "out" / "demo.tar.gz"
    out.parent.mkdir()
    run = subprocess.run(["bash", str(SCRIPT), str(demo), str(out)], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    parts = sorted(out.parent.iterdir())
    assert [p.name for p in parts] == ["demo.tar.gz.part-aa", "demo.tar.gz.part-ab"]
    assert parts[0].stat().st_size == 15 * 2**20 and parts[1].stat().st_size < 15 * 2**20
    assert "cat demo.tar.gz.part-* > demo.tar.gz" in run.stdout
    joined = tmp_path / "joined.tar.gz"
    joined.write_bytes(b"".join(p.read_bytes() for p in parts))
    with tarfile.open(joined) as tar:
        weights = tar.extractfile("./run/model.safetensors").read()
    assert weights == (demo / "run" / "model.safetensors").read_bytes()


def test_a_missing_folder_is_a_usage_error(tmp_path):
    run = subprocess.run(["bash", str(SCRIPT), str(tmp_path / "nowhere"), str(tmp_path / "x.tar.gz")],
                         capture_output=True, text=True)
    assert run.returncode == 2 and "usage" in run.stderr
