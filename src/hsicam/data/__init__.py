"""Hyperspectral data: readers/writers, resampling, normalisation, datasets, synthetic generator.

See :mod:`hsicam.data.formats` for the formats, :mod:`hsicam.data.cube` for the normalisation
policy, :mod:`hsicam.data.datasets` for training datasets and :mod:`hsicam.data.synthetic` for the
embedded dataset (which alone needs colour-science, and only while generating).
"""

from hsicam.data.cube import check_cube, normalize_per_cube_max, resample_cube
from hsicam.data.datasets import PatchDataset, SceneDataset, list_scenes, split_scenes
from hsicam.data.formats import (
    FORMATS,
    detect_format,
    read_arad,
    read_cave,
    read_cube,
    read_envi,
    read_harvard,
    read_hsicam_h5,
    read_icvl,
    read_kaist_exr,
    read_kaist_mat,
    read_npy,
    write_cube_h5,
    write_envi,
)
from hsicam.data.pipeline import build_datasets, dataset_root, heldout_root, make_loader, split_dataset

__all__ = [
    "FORMATS",
    "PatchDataset",
    "build_datasets",
    "dataset_root",
    "heldout_root",
    "make_loader",
    "split_dataset",
    "SceneDataset",
    "check_cube",
    "detect_format",
    "list_scenes",
    "normalize_per_cube_max",
    "read_arad",
    "read_cave",
    "read_cube",
    "read_envi",
    "read_harvard",
    "read_hsicam_h5",
    "read_icvl",
    "read_kaist_exr",
    "read_kaist_mat",
    "read_npy",
    "resample_cube",
    "split_scenes",
    "write_cube_h5",
    "write_envi",
]
