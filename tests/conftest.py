"""Shared fixtures of the physics test suite.

``tiny_config`` / ``tiny_camera`` build a DOE camera that runs in milliseconds: 3 bands
(500, 550, 600 nm), an 11×11-cell DOE (R = 0.25 mm, 50 µm cells), f = 5 mm and 10 µm pixels,
which gives a 7×7 PSF kernel and a 3×3 CFA period. Tests that are about the paper optics or
need fine sampling build their own configuration.
"""

from __future__ import annotations

import copy
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from hsicam.cameras import DOECamera
from hsicam.config import load_config


def _share_the_cores() -> None:
    """Under pytest-xdist (``make test``: 2 workers on the project's 2-core machines), each worker's torch
    takes its share of the cores instead of all of them: two workers each running 2 OpenMP threads on 2
    cores only spin against each other. The CLI subprocesses run on one thread already (``cli_env``)."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0") or 0)
    if workers > 1:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        torch.set_num_threads(max(1, cores // workers))


_share_the_cores()

TINY_CAMERA_OVERRIDES = (
    "bands.start_nm=500",
    "bands.stop_nm=600",
    "bands.step_nm=50",
    "camera.aperture_radius_mm=0.25",
    "camera.doe.cell_size_um=50",
    "camera.lens.focal_length_mm=5",
    "camera.sensor.pixel_pitch_um=10",
    "camera.cfa.period=3",
)


@pytest.fixture
def one_torch_thread():
    """torch on one thread for the test (small networks: threads cost more than they give), restored after."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture
def tiny_config():
    """Factory: ``tiny_config(*overrides)`` → validated :class:`hsicam.config.Config` of the tiny camera."""

    def make(*overrides: str):
        return load_config(overrides=[*TINY_CAMERA_OVERRIDES, *overrides])

    return make


@pytest.fixture
def tiny_camera(tiny_config):
    """Factory: ``tiny_camera(*overrides, dtype=torch.float32)`` → :class:`DOECamera` (tiny optics)."""

    def make(*overrides: str, dtype: torch.dtype = torch.float32) -> DOECamera:
        cam = DOECamera.from_config(tiny_config(*overrides))
        return cam.to(dtype)

    return make


@pytest.fixture
def clone_camera():
    """``clone_camera(cam, dtype)``: an independent copy of a camera converted to ``dtype``."""

    def make(cam: DOECamera, dtype: torch.dtype) -> DOECamera:
        return copy.deepcopy(cam).to(dtype)

    return make


@pytest.fixture(scope="module")
def cache_env(tmp_path_factory):
    """A private synthetic-data cache (``HSICAM_CACHE``) for one test module, generated once."""
    d = tmp_path_factory.mktemp("cache")
    old = os.environ.get("HSICAM_CACHE")
    os.environ["HSICAM_CACHE"] = str(d)
    yield d
    if old is None:
        os.environ.pop("HSICAM_CACHE", None)
    else:
        os.environ["HSICAM_CACHE"] = old


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """A 7-band .npy scene of the tiny preset's camera (a module that needs another defines its own)."""
    p = tmp_path_factory.mktemp("scene") / "scene.npy"
    np.save(p, np.random.default_rng(0).uniform(0.1, 1, (7, 40, 40)).astype(np.float32))
    return p


#: Lines for a script launched by torchrun: they keep the process group that ``fit`` creates, and
#: ``group_references()`` counts what else still refers to it once training has ended. A group still
#: referenced lives on to the interpreter's exit, where gloo's threads can abort the finished process:
#: so the script ends with ``release_the_group()``, which drops the list's own reference (else the test's
#: instrumentation is itself such a reference: a full suite saw torchrun fail with exit -6 once in session 40).
KEEP_THE_GROUP = """
import sys
import torch.distributed as dist
_groups = []
_init_process_group = dist.init_process_group
def _keep_the_group(*args, **kwargs):
    _init_process_group(*args, **kwargs)
    _groups.append(dist.distributed_c10d._get_default_group())
dist.init_process_group = _keep_the_group
def group_references():
    # all references but the list's and getrefcount's own argument; 0 when no group was created
    return sys.getrefcount(_groups[0]) - 2 if _groups else 0
def release_the_group():
    # the kept group freed now, not at the interpreter's exit (where gloo's threads can abort)
    _groups.clear()
"""


def torchrun_tmp(tmp_path: Path) -> Path:
    """A TMPDIR for a ``torch.distributed.run`` subprocess: torchelastic leaves a ``torchelastic_*``
    folder in the temporary directory of every launch, which belongs under the test's own folder."""
    d = tmp_path / "tmp"
    d.mkdir(exist_ok=True)
    return d
