"""The shared trained run of the fabrication, calibration and robustness tests, and the files it is built from.

``fab_run`` is a small trained run on the 3-band tiny optics (conftest) with a homogeneous dataset: built once per
pytest session (under the session's base temporary folder) and reused by every module that imports the fixture
(cameras/test_calibration.py, export/, data/test_reader_robustness.py, ...). ``write_homogeneous_scenes`` writes its
scenes, ``write_psf_dir`` a measured-PSF folder as `hsicam psf` writes it. Moved here from test_calibration.py when
the tests went into sub-folders, so that a test file of any folder imports them without importing another test file."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from conftest import TINY_CAMERA_OVERRIDES
from hsicam.config import load_config
from hsicam.io import write_json, write_npy
from hsicam.spectral import Bands

FAB_OVERRIDES = (
    *TINY_CAMERA_OVERRIDES,
    "model.rdn.features=16", "model.rdn.growth=8",
    "data.val_fraction=0.25", "data.patches_per_epoch=32", "data.val_patches=8", "data.patch_px=16",
    "train.epochs=20", "train.lr=0.003", "train.doe_lr_nm=0.000001", "train.cfa_lr=0.000001",
)




def write_homogeneous_scenes(folder: Path, n: int = 8, size: int = 40) -> Path:
    """n scenes on 500/550/600 nm: smooth random abundances of three fixed smooth spectra."""
    from hsicam.data import write_cube_h5

    folder.mkdir(parents=True, exist_ok=True)
    bands = Bands.uniform(500, 600, 50)
    lam = bands.centers_nm
    spectra = np.stack([np.exp(-0.5 * ((lam - mu) / 40.0) ** 2) + 0.1 for mu in (480.0, 550.0, 620.0)])
    for i in range(n):
        low = torch.rand(1, 3, size // 8 + 1, size // 8 + 1, generator=torch.Generator().manual_seed(i))
        ab = F.interpolate(low, size=(size, size), mode="bilinear", align_corners=True)[0].numpy() ** 3
        cube = np.einsum("khw,kc->chw", ab, spectra)
        write_cube_h5(folder / f"s{i:02d}.h5", (cube / cube.max()).astype(np.float32), bands)
    return folder


def make_fab_run(tmp_path_factory) -> Path:
    """The shared trained run (built once per pytest session, reused by the other modules)."""
    from hsicam.engine.train import train

    base = tmp_path_factory.getbasetemp() / "hsicam_fab"
    run = base / "run"
    if (run / "model.safetensors").is_file():
        return run
    shutil.rmtree(base, ignore_errors=True)
    data = write_homogeneous_scenes(base / "data")
    cfg = load_config("tiny", [*FAB_OVERRIDES, f"data.root={data}"])
    train(cfg, run, progress=False)
    return run


@pytest.fixture(scope="module")
def fab_run(tmp_path_factory):
    return make_fab_run(tmp_path_factory)


def design_psf_dir(run: Path, d: Path, bands: Bands, pitch_um: float = 10.0) -> Path:
    """A measured-PSF folder (:func:`write_psf_dir`) holding ``run``'s own design PSFs, axis-centred energy fractions:
    a fine-tuning from it changes nothing optical."""
    from hsicam.runs.folder import load_run

    _, base = load_run(run)
    with torch.no_grad():
        psf = base.camera.psf().double().numpy()
    k = psf.shape[-1]
    return write_psf_dir(d, psf, bands, pitch_um, centre="axis", axis_px=[k // 2, k // 2], normalize="none")


def write_psf_dir(d: Path, psf: np.ndarray, bands: Bands, pitch_um: float, **meta) -> Path:
    """A measured-PSF folder holding the stack as psf.npy + psf.json (what `hsicam psf` writes)."""
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir(parents=True)
    write_npy(d / "psf.npy", np.asarray(psf, dtype=np.float32))
    write_json(d / "psf.json", {"pixel_pitch_um": pitch_um, "bands_nm": bands.centers_nm.tolist(), **meta})
    return d
