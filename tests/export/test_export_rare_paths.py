"""Lines of the fabrication export and tolerance modules (export/doe.py, export/tolerance.py, optics/perturb.py) that
the default suite never ran (coverage audits; moved from report/test_report_rare_paths.py,
models/test_models_rare_paths.py and data/test_data_sources_rare_paths.py): each checked against the exact text a
user sees and the folder left empty, a file read back in its real format, or a loop."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cli_helpers import entries
from hsicam.errors import InputError
from hsicam.optics.perturb import shift_fill


# ------------------------------------------------------------------------------------------------
# export/doe.py
# ------------------------------------------------------------------------------------------------
def test_height_tiff_refuses_negative_heights_and_writes_nothing(tmp_path):
    from hsicam.export.doe import write_height_tiff

    with pytest.raises(InputError) as info:
        write_height_tiff(tmp_path / "h.tif", np.array([[0.0, 10.0], [-0.5, 3.0]]), 30.0, {})
    assert str(info.value) == "heights must be >= 0 for the 16-bit TIFF"
    assert entries(tmp_path) == []


# --- optics/perturb.py: a shift of the whole array or more leaves zeros ------------------------------------------
def test_shift_fill_by_the_size_or_more_is_all_zeros_and_smaller_shifts_match_a_loop():
    x = torch.arange(1.0, 13.0).reshape(3, 4)
    for dy, dx in ((3, 0), (0, -4), (-5, 1)):
        assert torch.equal(shift_fill(x, dy, dx), torch.zeros(3, 4))
    for dy, dx in ((1, -2), (-2, 3)):
        ref = torch.zeros(3, 4)
        for i in range(3):
            for j in range(4):
                if 0 <= i - dy < 3 and 0 <= j - dx < 4:
                    ref[i, j] = x[i - dy, j - dx]
        assert torch.equal(shift_fill(x, dy, dx), ref)


# --- export/tolerance.py, export/doe.py (session 58, cov12a: moved from data/test_data_sources_rare_paths.py) -------
@pytest.mark.parametrize("doc,kind", [("[1, 2]", "list"), ("3.5", "float"), ('"x"', "str"), ("null", "NoneType")])
def test_a_tolerance_json_that_is_no_object_is_refused_in_one_line(tmp_path, doc, kind):
    from hsicam.export.tolerance import read_tolerance_study

    path = tmp_path / "tolerance.json"
    path.write_text(doc)
    with pytest.raises(InputError) as info:
        read_tolerance_study(path, tmp_path)
    assert str(info.value) == (f"{path}: not an hsicam tolerance study (a JSON {kind}, not an object); pass the "
                               "tolerance.json that `hsicam tolerance --run RUN --out DIR` writes")


def test_an_all_zero_doe_exports_zero_tiffs_at_one_nm_per_count(tiny_config, tmp_path):
    """A flat element (no relief): nice_scale(0) is 1 nm per count; both TIFFs read back all zero, the levels
    all 0, and the height range [0, 0]."""
    from hsicam.cameras import DOECamera
    from hsicam.export.doe import export_doe, nice_scale, read_height_tiff

    assert nice_scale(0.0) == 1.0 and nice_scale(-3.0) == 1.0 and nice_scale(float("nan")) == 1.0
    cam = DOECamera.from_config(tiny_config())
    with torch.no_grad():
        for name, p in cam.named_parameters():
            if "doe" in name:
                p.zero_()
    out = tmp_path / "fab"
    out.mkdir()
    facts = export_doe(cam, out, 4, cam.bands.centers_nm)
    assert facts["tiff_scale_nm_per_count"] == 1.0 and facts["height_range_nm"] == [0.0, 0.0]
    for name in ("doe_height_nm.tif", "doe_height_L4_nm.tif"):
        h, desc = read_height_tiff(out / name)
        assert not h.any() and desc["scale_nm_per_count"] == 1.0, name
    assert not np.load(out / "doe_level_L4.npy").any()
