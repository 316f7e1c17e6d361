"""Hyperspectral data: readers/writers, resampling, normalisation, datasets, synthetic generator.

See :mod:`hsicam.data.formats` for the formats, :mod:`hsicam.data.cube` for the normalisation
policy, :mod:`hsicam.data.datasets` for training datasets and :mod:`hsicam.data.synthetic` for the
embedded dataset (which alone needs colour-science, and only while generating).

The names below are loaded from their modules on first use (PEP 562), so that importing a light
module of this package (``hsicam.data.estimates``, which the command line's parser reads) does not
import torch with the datasets.
"""

from __future__ import annotations

import importlib
import importlib.util
from typing import Any

#: Each public name of the package → the module that defines it.
_HOMES = {
    "hsicam.data.cube": ("check_cube", "normalize_per_cube_max", "resample_cube"),
    "hsicam.data.datasets": ("PatchDataset", "SceneDataset", "list_scenes", "split_scenes"),
    "hsicam.data.formats": ("FORMATS", "detect_format", "read_arad", "read_cave", "read_cube", "read_envi",
                            "read_harvard", "read_hsicam_h5", "read_icvl", "read_kaist_exr", "read_kaist_mat",
                            "read_npy", "write_cube_h5", "write_envi"),
    "hsicam.data.pipeline": ("build_datasets", "dataset_root", "heldout_root", "make_loader", "split_dataset"),
}
_HOME_OF = {name: module for module, names in _HOMES.items() for name in names}

__all__ = sorted(_HOME_OF)


def __getattr__(name: str) -> Any:
    """``hsicam.data.NAME`` from its module, imported now; a sub-module's name (``hsicam.data.formats``) imports that
    sub-module, as the package's eager imports used to make them attributes."""
    module = _HOME_OF.get(name)
    if module is not None:
        value = getattr(importlib.import_module(module), name)
    elif importlib.util.find_spec(f"{__name__}.{name}") is not None:
        value = importlib.import_module(f"{__name__}.{name}")
    else:
        raise AttributeError(f"module 'hsicam.data' has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
