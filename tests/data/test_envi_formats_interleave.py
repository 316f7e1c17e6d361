"""An ENVI header without 'interleave' (session 71, a helper's hunt): its data were read as bsq without a word, so a
bip file lost its header key read back scrambled. Reference: the cube written here in each order by NumPy."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from envi_files import write_envi_pair
from hsicam.data import read_cube

WAVES = [450.0, 550.0, 650.0]


def _without_interleave(hdr):
    hdr.write_text("".join(line for line in hdr.read_text().splitlines(keepends=True)
                           if not line.startswith("interleave")))


@pytest.mark.parametrize("stored", ["bsq", "bip"])
def test_a_header_without_interleave_is_read_as_bsq_and_said(tmp_path, caplog, stored):
    cube = np.arange(3 * 4 * 5, dtype=np.float32).reshape(3, 4, 5) + 1
    hdr = write_envi_pair(tmp_path, cube, "", WAVES, dtype="<f4", code=4, interleave=stored)
    _without_interleave(hdr)
    with caplog.at_level(logging.WARNING, logger="hsicam.data.formats"):
        got, bands, _ = read_cube(hdr)
    [rec] = caplog.records
    assert rec.getMessage() == (f"{hdr}: the header has no 'interleave'; reading the data as bsq (band after band, "
                                "ENVI's and GDAL's default): if the images look scrambled, add 'interleave = bil' or "
                                "'interleave = bip'")
    assert np.array_equal(got, cube) == (stored == "bsq")  # the bip file, read as bsq: scrambled, hence the warning
    np.testing.assert_array_equal(bands.centers_nm, WAVES)


@pytest.mark.parametrize("shape, stored", [((3, 1, 5), "bip"), ((3, 5, 1), "bil"), ((3, 5, 1), "bip")])
def test_a_one_row_or_one_column_header_without_interleave_is_warned_about_too(tmp_path, caplog, shape, stored):
    """One line or one sample is not one order: bip of one row, bil or bip of one column differ from bsq (a review,
    session 71); the warning comes once per file, however often a dataset reads it."""
    cube = np.arange(np.prod(shape), dtype=np.float32).reshape(shape) + 1
    hdr = write_envi_pair(tmp_path, cube, "", WAVES, dtype="<f4", code=4, interleave=stored)
    _without_interleave(hdr)
    with caplog.at_level(logging.WARNING, logger="hsicam.data.formats"):
        got, _, _ = read_cube(hdr)
        read_cube(hdr)
    assert len(caplog.records) == 1 and "has no 'interleave'" in caplog.records[0].getMessage()
    assert not np.array_equal(got, cube)


def test_a_one_band_header_without_interleave_is_read_without_a_word(tmp_path, caplog):
    cube = np.arange(20, dtype=np.float32).reshape(1, 4, 5) + 1
    hdr = write_envi_pair(tmp_path, cube, "", WAVES, dtype="<f4", code=4, interleave="bip")
    _without_interleave(hdr)
    with caplog.at_level(logging.WARNING, logger="hsicam.data.formats"):
        got, _, _ = read_cube(hdr)
    assert not caplog.records  # one band: every order is the same bytes
    np.testing.assert_array_equal(got, cube)
