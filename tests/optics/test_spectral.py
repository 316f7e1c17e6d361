"""Band grids, spectral resampling and refractive indices (against published values)."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from hsicam.errors import InputError
from hsicam.spectral import Bands, FusedSilica, TabulatedMaterial, get_material, resample_spectra


# --------------------------------------------------------------------------------------------
# Bands
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "centers, fwhm",
    [
        ([], []),  # no band
        ([500.0, 490.0], [10.0, 10.0]),  # descending
        ([500.0, 500.0], [10.0, 10.0]),  # repeated
        ([-5.0, 500.0], [10.0, 10.0]),  # negative wavelength
        ([0.0, 500.0], [10.0, 10.0]),  # zero wavelength
        ([np.nan, 500.0], [10.0, 10.0]),  # NaN
        ([500.0, np.inf], [10.0, 10.0]),  # Inf
        ([500.0, 510.0], [10.0, 10.0, 10.0]),  # FWHM count mismatch
        ([500.0, 510.0], [10.0, 0.0]),  # zero FWHM
        ([500.0, 510.0], [10.0, -1.0]),  # negative FWHM
    ],
)
def test_bands_rejects_invalid_grids(centers, fwhm):
    with pytest.raises(InputError):
        Bands(np.asarray(centers, dtype=float), np.asarray(fwhm, dtype=float))


def test_bands_scalar_fwhm_broadcasts():
    b = Bands(np.array([500.0, 510.0, 520.0]), np.array([7.0]))
    np.testing.assert_array_equal(b.fwhm_nm, [7.0, 7.0, 7.0])


def test_bands_are_immutable():
    b = Bands.uniform(500, 520, 10)
    with pytest.raises(ValueError):
        b.centers_nm[0] = 1.0


def test_uniform_grid_is_the_paper_grid():
    b = Bands.uniform(420, 720, 10)
    assert len(b) == 31
    np.testing.assert_allclose(b.centers_nm, 420.0 + 10.0 * np.arange(31), rtol=0, atol=1e-9)
    np.testing.assert_allclose(b.fwhm_nm, 10.0)
    assert b.min_nm == 420.0 and b.max_nm == 720.0
    assert Bands.paper() == b
    np.testing.assert_allclose(b.wavelengths_m().numpy(), b.centers_nm * 1e-9, rtol=1e-15)
    assert b.wavelengths_m().dtype == torch.float64 and b.wavelengths_m(dtype=torch.float32).dtype == torch.float32


@pytest.mark.parametrize("start, stop, step", [(420, 725, 10), (500, 400, 10), (420, 720, 0), (420, 720, -10)])
def test_uniform_grid_rejects_bad_steps(start, stop, step):
    with pytest.raises(InputError):
        Bands.uniform(start, stop, step)


def test_uniform_grid_refuses_a_band_count_no_camera_has_before_building_it():
    """A mistyped step (1e-6 nm: 3e8 bands) built the grid, then gigabytes of band arrays, and was
    killed by the kernel before the memory plan could refuse it (probe 22); 10 000 bands still work."""
    from hsicam.config import load_config
    from hsicam.errors import ConfigError
    from hsicam.spectral.bands import MAX_UNIFORM_BANDS

    assert len(Bands.uniform(1.0, float(MAX_UNIFORM_BANDS), 1.0)) == MAX_UNIFORM_BANDS
    with pytest.raises(InputError, match=r"^Bands.uniform: 420..720 nm in steps of 1e-06 nm gives 300,000,001 bands, "
                                         r"more than 10000; check the step \(in nm\)$"):
        Bands.uniform(420, 720, 1e-6)
    with pytest.raises(ConfigError, match=r"^bands.start_nm, bands.stop_nm, bands.step_nm \(420, 720, 1e-05\): .* gives 30,000,001 bands"):
        load_config("tiny", ["bands.step_nm=1e-5"])
    # a subnormal step: the band count is infinite (it was Python's 'cannot convert float infinity to integer')
    with pytest.raises(InputError, match=r"^Bands.uniform: 420..720 nm in steps of \S+ nm gives infinitely many "
                                         r"bands, more than 10000; check the step \(in nm\)$"):
        Bands.uniform(420, 720, 1e-320)


def test_bands_dict_round_trip_and_matching():
    b = Bands.uniform(450, 650, 25, fwhm_nm=12.0)
    assert Bands.from_dict(b.to_dict()) == b
    assert not b.matches(Bands.uniform(450, 650, 50))
    # text where numbers belong is the Bands' own error (was numpy's ValueError); the constructor's own stays
    with pytest.raises(InputError, match="^Bands: centers_nm and fwhm_nm must be lists of numbers"):
        Bands.from_dict({"centers_nm": "abc", "fwhm_nm": 1})
    with pytest.raises(InputError) as exc:
        Bands.from_dict({"centers_nm": [500, 400], "fwhm_nm": [10, 10]})
    assert "must be lists of numbers" not in str(exc.value)


def test_uniform_grid_names_a_value_that_is_not_a_finite_number():
    for args, said in (((float("nan"), 700, 10), "start_nm nan"), ((400, float("inf"), 10), "stop_nm inf"),
                       ((400, 700, float("nan")), "step_nm nan"), ((400, "700", 10), "stop_nm '700'")):
        with pytest.raises(InputError, match=r"^Bands.uniform: start, stop and step must be finite numbers \(nm\), got "
                                             + re.escape(said) + "$"):
            Bands.uniform(*args)


def test_a_grid_of_more_decimals_than_a_file_keeps_is_still_that_grid_read_back(tmp_path):
    """A file lists band centres to 1e-3 nm (ENVI headers, and every reader's rounding); a grid of more decimals
    written and read back was refused at its end (720.0004 not covered by 720) or resampled. Grids within half of
    that (BAND_TOL_NM) are one grid: the cube comes back as written."""
    from hsicam.data import read_cube, write_envi
    from hsicam.data.cube import conform_bands
    from hsicam.spectral.bands import BAND_TOL_NM

    assert BAND_TOL_NM == 5e-4
    bands = Bands.from_centers(np.linspace(420.0, 720.0004, 31), 10.0)
    cube = np.random.default_rng(0).random((31, 6, 5)).astype(np.float32)
    hdr, _ = write_envi(tmp_path / "c.hdr", cube, bands)
    back, back_bands, _ = read_cube(hdr)
    assert back_bands.max_nm == 720.0 and back_bands.matches(bands) and back_bands.covers(bands)
    assert conform_bands(back, back_bands, bands, hdr) is back
    # 1e-3 nm apart is another grid (resampled), and 1e-3 nm beyond the data is refused
    shifted = Bands.from_centers(bands.centers_nm + 1e-3, 10.0)
    assert not back_bands.matches(shifted) and not back_bands.covers(shifted)


# --------------------------------------------------------------------------------------------
# Resampling
# --------------------------------------------------------------------------------------------
def test_resampling_is_exact_on_linear_spectra_numpy():
    src = Bands.uniform(400, 700, 10)
    dst = Bands.from_centers([403.0, 455.5, 512.25, 600.0, 699.9])
    a, b = 0.25, 1.5e-3
    values = np.stack([a + b * src.centers_nm, -2.0 + 4e-3 * src.centers_nm])  # (2, C): band axis 1
    out = resample_spectra(values, src, dst, axis=1)
    expected = np.stack([a + b * dst.centers_nm, -2.0 + 4e-3 * dst.centers_nm])
    np.testing.assert_allclose(out, expected, rtol=0, atol=1e-12)


def test_resampling_is_exact_on_linear_spectra_torch_and_differentiable():
    src = Bands.uniform(420, 720, 30)  # coarse grid
    dst = Bands.uniform(425, 715, 5)
    lam = torch.tensor(np.array(src.centers_nm))
    cube = (0.1 + 2e-3 * lam)[:, None, None] * torch.ones(len(src), 3, 4, dtype=torch.float64)
    cube.requires_grad_(True)
    out = resample_spectra(cube, src, dst, axis=0)
    expected = (0.1 + 2e-3 * torch.tensor(np.array(dst.centers_nm)))[:, None, None].expand(len(dst), 3, 4)
    torch.testing.assert_close(out, expected, rtol=0, atol=1e-12)
    out.sum().backward()
    assert cube.grad is not None and torch.isfinite(cube.grad).all()
    # each destination band is a convex combination: total weight is preserved
    torch.testing.assert_close(cube.grad.sum(), torch.tensor(float(len(dst) * 12), dtype=torch.float64))


def test_resampling_same_grid_is_identity():
    b = Bands.uniform(500, 600, 10)
    v = np.random.default_rng(0).random(len(b))
    np.testing.assert_array_equal(resample_spectra(v, b, b), v)


@pytest.mark.parametrize("dst", [Bands.uniform(400, 700, 10), Bands.uniform(420, 730, 10)])
def test_resampling_outside_the_source_range_is_an_error(dst):
    src = Bands.uniform(420, 720, 10)
    with pytest.raises(InputError, match="not covered"):
        resample_spectra(np.zeros(len(src)), src, dst)


def test_resampling_wrong_axis_length_is_an_error():
    src = Bands.uniform(420, 720, 10)
    with pytest.raises(InputError):
        resample_spectra(np.zeros((5, len(src))), src, Bands.uniform(430, 710, 10), axis=0)


# --------------------------------------------------------------------------------------------
# Materials
# --------------------------------------------------------------------------------------------
# Fused silica, published indices (Malitson 1965; refractiveindex.info; Corning 7980 / Schott
# Lithosil catalogues, 4-5 decimals): Fraunhofer h, g, F, d, C lines, HeNe and Nd:YAG.
FUSED_SILICA_PUBLISHED = [
    (404.66, 1.46962),
    (435.83, 1.46669),
    (486.13, 1.46313),
    (587.56, 1.45846),
    (632.8, 1.45702),
    (656.27, 1.45637),
    (1064.0, 1.44963),
]


@pytest.mark.parametrize("wavelength_nm, n_published", FUSED_SILICA_PUBLISHED)
def test_fused_silica_matches_published_indices(wavelength_nm, n_published):
    assert FusedSilica().n(wavelength_nm) == pytest.approx(n_published, abs=6e-5)


def test_fused_silica_abbe_number():
    nd, nf, nc = FusedSilica().n(np.array([587.56, 486.13, 656.27]))
    assert (nd - 1) / (nf - nc) == pytest.approx(67.8, abs=0.1)  # published V_d = 67.8


def test_fused_silica_normal_dispersion_and_range():
    lam = np.linspace(420, 720, 31)
    n = FusedSilica().n(lam)
    assert n.shape == lam.shape and np.all(np.diff(n) < 0)
    with pytest.raises(InputError):
        FusedSilica().n(150.0)
    assert isinstance(get_material("fused_silica"), FusedSilica)


def test_tabulated_material_from_csv(tmp_path):
    path = tmp_path / "glass.csv"
    path.write_text("wavelength_nm,n\n400,1.60\n500,1.55\n700,1.51\n", encoding="utf-8")
    mat = get_material(str(path))
    assert isinstance(mat, TabulatedMaterial) and mat.name == "glass"
    np.testing.assert_allclose(mat.n(np.array([400.0, 450.0, 500.0, 600.0, 700.0])),
                               [1.60, 1.575, 1.55, 1.53, 1.51], rtol=0, atol=1e-12)
    with pytest.raises(InputError):
        mat.n(720.0)  # no extrapolation


@pytest.mark.parametrize(
    "text",
    [
        "lambda,n\n400,1.5\n500,1.4\n",  # wrong header
        "wavelength_nm,n\n400,abc\n500,1.4\n",  # non-numeric
        "wavelength_nm,n\n500,1.5\n400,1.4\n",  # not ascending
        "wavelength_nm,n\n400,0.9\n500,1.4\n",  # n < 1
        "wavelength_nm,n\n400,1.5\n",  # a single row
    ],
)
def test_tabulated_material_rejects_bad_tables(tmp_path, text):
    path = tmp_path / "bad.csv"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(InputError):
        TabulatedMaterial.from_csv(path)


def test_a_material_table_with_a_header_only_says_so(tmp_path):
    """It was told it lacked the columns its header names (session 37's hunt)."""
    path = tmp_path / "empty.csv"
    path.write_text("wavelength_nm,n\n", encoding="utf-8")
    with pytest.raises(InputError, match=r"empty.csv: the material table has 0 row\(s\) under its header; it needs two"):
        TabulatedMaterial.from_csv(path)


def test_unknown_material_and_missing_file(tmp_path):
    with pytest.raises(InputError):
        get_material("unobtainium")
    with pytest.raises(InputError):
        get_material(str(tmp_path / "missing.csv"))


def test_bands_from_dict_missing_key_and_comparison_with_another_type():
    with pytest.raises(InputError) as exc:
        Bands.from_dict({"centers_nm": [500.0]})
    assert str(exc.value) == "Bands: missing key 'fwhm_nm'"
    assert (Bands.paper() == "paper") is False and (Bands.paper() != 3) is True
