"""CASSI cameras: adjointness, shapes, loop references of the forward models, apertures, dispersion."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from cassi_reference import cassi, cassi_bands, loop_gram_diagonal
from hsicam.cameras import CodedAperture, DDCASSICamera, SDCASSICamera, build_camera
from hsicam.cameras.cassi import hashed_uniform, linear_dispersion, prism_dispersion, random_aperture
from hsicam.config import load_config
from hsicam.errors import ConfigError, InputError
from hsicam.models import CameraSystem
from hsicam.spectral import Bands

KINDS = ("dd_cassi", "sd_cassi")
CONVENTIONS = ("sum", "mean")


def cfg_of(kind: str, *overrides: str):
    """Five bands (500..700 nm), tiny everything else."""
    return load_config(overrides=["bands.start_nm=500", "bands.stop_nm=700", "bands.step_nm=50",
                                  f"camera.kind={kind}", *overrides])


def camera(kind: str, *overrides: str, dtype=torch.float64):
    return build_camera(cfg_of(kind, *overrides)).to(dtype)


# --------------------------------------------------------------------------------------------
# Independent loop references (written from the definitions, not from the implementation)
# --------------------------------------------------------------------------------------------
def dd_reference(x: np.ndarray, aperture: np.ndarray, shifts: list[int], scale: float) -> np.ndarray:
    """y[b, i, j] = s · Σ_c P[i, j + d_c] · x[b, c, i, j]."""
    b, c, h, w = x.shape
    y = np.zeros((b, 1, h, w))
    for n in range(b):
        for i in range(h):
            for j in range(w):
                y[n, 0, i, j] = scale * sum(aperture[i, j + shifts[k]] * x[n, k, i, j] for k in range(c))
    return y


def sd_reference(x: np.ndarray, aperture: np.ndarray, shifts: list[int], scale: float) -> np.ndarray:
    """The coded band c lands on sensor columns j + d_c: y[b, i, j + d_c] += s · P[i, j] · x[b, c, i, j]."""
    b, c, h, w = x.shape
    y = np.zeros((b, 1, h, w + max(shifts)))
    for n in range(b):
        for k in range(c):
            for i in range(h):
                for j in range(w):
                    y[n, 0, i, j + shifts[k]] += scale * aperture[i, j] * x[n, k, i, j]
    return y


# --------------------------------------------------------------------------------------------
# Adjointness, shapes
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("convention", CONVENTIONS)
@pytest.mark.parametrize("dispersion", ("linear", "prism"))
def test_adjoint_identity_float64(kind, convention, dispersion):
    cam = camera(kind, f"camera.cassi.convention={convention}", f"camera.cassi.dispersion={dispersion}")
    g = torch.Generator().manual_seed(1)
    x = torch.randn(2, 5, 13, 17, generator=g, dtype=torch.float64)
    y = torch.randn(2, 1, *cam.sensor_size((13, 17)), generator=g, dtype=torch.float64)
    ax = cam.A(x)
    assert ax.shape == y.shape
    lhs, rhs = (ax * y).sum(), (x * cam.A_adjoint(y)).sum()
    assert abs(lhs - rhs) / abs(lhs) < 1e-6


@pytest.mark.parametrize("shift", (1.0, 2.0, 3.0))
@pytest.mark.parametrize("convention", CONVENTIONS)
def test_sd_cassi_width_and_shapes(shift, convention):
    cam = camera("sd_cassi", f"camera.cassi.shift_px={shift}", f"camera.cassi.convention={convention}")
    c, h, w = 5, 9, 20
    y = cam.A(torch.rand(3, c, h, w, dtype=torch.float64))
    assert y.shape == (3, 1, h, w + (c - 1) * int(shift))
    assert cam.sensor_size((h, w)) == (h, w + (c - 1) * int(shift))
    assert cam.scene_size(cam.sensor_size((h, w))) == (h, w)
    assert cam.A_adjoint(y).shape == (3, c, h, w)
    assert cam.margin == 0


@pytest.mark.parametrize("boundary", ("valid", "same"))
def test_dd_cassi_measurement_has_the_scene_size(boundary):
    cam = camera("dd_cassi", f"camera.boundary={boundary}")
    x = torch.rand(2, 5, 11, 14, dtype=torch.float64)
    assert cam.A(x).shape == (2, 1, 11, 14)
    assert cam.sensor_size((11, 14)) == (11, 14) and cam.margin == 0
    assert cam.A_adjoint(cam.A(x)).shape == x.shape


def test_mst_convention_matches_shift_then_sum():
    """SD-CASSI with 2 px per band and a sum is MST's `sum(shift(mask3d * x, 2), bands)`."""
    cam = camera("sd_cassi", "camera.cassi.shift_px=2", "camera.cassi.convention=sum")
    x = torch.rand(1, 5, 8, 10, dtype=torch.float64)
    mask = cam.aperture.pattern(8, 10, dtype=torch.float64)
    coded = (mask * x)[0].numpy()
    shifted = np.zeros((5, 8, 10 + 2 * 4))
    for c in range(5):  # MST's shift(): output[:, c, :, 2c : 2c + W] = input[:, c]
        shifted[c, :, 2 * c : 2 * c + 10] = coded[c]
    np.testing.assert_allclose(cam.A(x)[0, 0].numpy(), shifted.sum(0), rtol=1e-12, atol=1e-12)


# --------------------------------------------------------------------------------------------
# Forward models against the loop references
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("convention", CONVENTIONS)
@pytest.mark.parametrize("shift", (1.0, 2.0))
def test_dd_cassi_matches_loop_reference(convention, shift):
    cam = camera("dd_cassi", f"camera.cassi.convention={convention}", f"camera.cassi.shift_px={shift}")
    x = torch.rand(2, 5, 6, 7, dtype=torch.float64)
    shifts = [round(shift * c) for c in range(5)]
    aperture = cam.aperture.pattern(6, 7 + max(shifts), dtype=torch.float64).numpy()
    scale = 1 / 5 if convention == "mean" else 1.0
    np.testing.assert_allclose(cam.A(x).numpy(), dd_reference(x.numpy(), aperture, shifts, scale), rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("convention", CONVENTIONS)
@pytest.mark.parametrize("dispersion", ("linear", "prism"))
def test_sd_cassi_matches_loop_reference(convention, dispersion):
    cam = camera("sd_cassi", f"camera.cassi.convention={convention}", f"camera.cassi.dispersion={dispersion}",
                 "camera.cassi.prism_focal_length_mm=5")
    x = torch.rand(2, 5, 6, 7, dtype=torch.float64)
    shifts = list(cam.shifts)
    aperture = cam.aperture.pattern(6, 7, dtype=torch.float64).numpy()
    scale = 1 / 5 if convention == "mean" else 1.0
    np.testing.assert_allclose(cam.A(x).numpy(), sd_reference(x.numpy(), aperture, shifts, scale), rtol=1e-12, atol=1e-14)


def test_each_dd_band_sees_the_aperture_shifted_by_its_dispersion():
    cam = camera("dd_cassi")
    h, w = 7, 9
    masks = cam.band_masks(h, w, dtype=torch.float64)
    big = cam.aperture.pattern(h, w + 8, dtype=torch.float64)
    for c in range(5):
        torch.testing.assert_close(masks[c], big[:, 2 * c : 2 * c + w])
    # a delta in band c at (i, j) shows up at (i, j) weighted by P(i, j + d_c)
    x = torch.zeros(1, 5, h, w, dtype=torch.float64)
    x[0, 3, 2, 4] = 1.0
    y = cam.A(x)
    assert y[0, 0, 2, 4] == pytest.approx(float(big[2, 4 + 6]) / 5)
    assert (y != 0).sum() <= 1


def test_sd_cassi_float32_and_float64_agree():
    c64, c32 = camera("sd_cassi"), camera("sd_cassi", dtype=torch.float32)
    x = torch.rand(1, 5, 16, 16, dtype=torch.float64)
    torch.testing.assert_close(c32.A(x.float()).double(), c64.A(x), rtol=1e-5, atol=1e-6)
    assert c32.A(x.float()).dtype == torch.float32


@pytest.mark.parametrize("kind", KINDS)
def test_gradcheck(kind):
    cam = camera(kind)
    x = torch.rand(1, 5, 4, 5, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(cam.A, (x,))
    y = torch.rand(1, 1, *cam.sensor_size((4, 5)), dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(cam.A_adjoint, (y,))


# --------------------------------------------------------------------------------------------
# Coded aperture
# --------------------------------------------------------------------------------------------
def test_random_aperture_is_binary_deterministic_and_crop_consistent():
    a = random_aperture(64, 80, seed=3)
    assert set(a.unique().tolist()) <= {0.0, 1.0}
    torch.testing.assert_close(random_aperture(64, 80, seed=3), a)
    torch.testing.assert_close(random_aperture(200, 300, seed=3)[:64, :80], a)
    assert not torch.equal(random_aperture(64, 80, seed=4), a)


def test_random_aperture_statistics():
    u = hashed_uniform(256, 256, seed=0)
    assert 0 <= float(u.min()) and float(u.max()) < 1
    # uniform: mean 1/2, variance 1/12; neighbours uncorrelated
    assert abs(float(u.mean()) - 0.5) < 0.005
    assert abs(float(u.var()) - 1 / 12) < 0.002
    for du, dv in ((0, 1), (1, 0), (1, 1)):
        a, b = u[: 256 - du, : 256 - dv], u[du:, dv:]
        corr = float(((a - a.mean()) * (b - b.mean())).mean() / (a.std() * b.std()))
        assert abs(corr) < 0.01
    for density in (0.25, 0.5, 0.9):
        assert abs(float(random_aperture(256, 256, 1, density).mean()) - density) < 0.01


def test_aperture_from_file(tmp_path):
    arr = (np.random.default_rng(0).random((12, 30)) > 0.5).astype(np.float32)
    np.save(tmp_path / "mask.npy", arr)
    cam = camera("dd_cassi", f"camera.cassi.mask_file={tmp_path / 'mask.npy'}")
    np.testing.assert_array_equal(cam.aperture.pattern(12, 18).numpy(), arr[:, :18])
    x = torch.rand(1, 5, 12, 10, dtype=torch.float64)
    np.testing.assert_allclose(cam.A(x).numpy(), dd_reference(x.numpy(), arr.astype(np.float64), [0, 2, 4, 6, 8], 0.2),
                               rtol=1e-12)
    with pytest.raises(InputError, match="needed"):
        cam.A(torch.rand(1, 5, 12, 23, dtype=torch.float64))  # needs 23 + 8 columns
    with pytest.raises(InputError, match="needed"):
        cam.A(torch.rand(1, 5, 13, 10, dtype=torch.float64))


@pytest.mark.parametrize("content, match", [(np.full((4, 4), 2.0), "in \\[0, 1\\]"), (np.zeros(5), "2-D"),
                                            (np.full((4, 4), np.nan), "finite"),
                                            (np.zeros((64, 96)), "closed everywhere")])
def test_bad_aperture_files(tmp_path, content, match):
    np.save(tmp_path / "bad.npy", content)
    with pytest.raises(InputError, match=match):
        camera("dd_cassi", f"camera.cassi.mask_file={tmp_path / 'bad.npy'}")


def test_missing_aperture_file(tmp_path):
    with pytest.raises(InputError, match="no such"):
        camera("sd_cassi", f"camera.cassi.mask_file={tmp_path / 'nope.npy'}")


# --------------------------------------------------------------------------------------------
# Dispersion
# --------------------------------------------------------------------------------------------
def test_linear_dispersion():
    assert linear_dispersion(5, 2.0) == [0, 2, 4, 6, 8]
    # halves round up, so the steps stay even (Python's round, half to even, gave [0, 2, 3, 4, 6])
    assert linear_dispersion(5, 1.5) == [0, 2, 3, 5, 6]
    assert linear_dispersion(4, 0.5) == [0, 1, 1, 2]


def _fused_silica_n(lam_nm: np.ndarray) -> np.ndarray:
    """Malitson 1965, written out here independently of hsicam.spectral."""
    l2 = (lam_nm * 1e-3) ** 2
    return np.sqrt(1 + 0.6961663 * l2 / (l2 - 0.0684043**2) + 0.4079426 * l2 / (l2 - 0.1162414**2)
                   + 0.8974794 * l2 / (l2 - 9.896161**2))


def test_prism_dispersion_thin_prism_reference():
    bands = Bands.uniform(420, 720, 10)
    d = prism_dispersion(bands, "fused_silica", 30.0, 0.05, 6e-6)
    n = _fused_silica_n(bands.centers_nm)
    expected = 0.05 * np.tan((n[0] - n) * math.radians(30.0)) / 6e-6
    assert d == [int(v) for v in np.round(expected)]
    assert d[0] == 0 and all(b >= a for a, b in zip(d, d[1:]))
    steps = np.diff(d)
    assert steps[:5].sum() > 2 * steps[-5:].sum()  # blue spreads more than red
    assert 40 < d[-1] < 80


def test_prism_config_reaches_the_camera():
    cam = camera("dd_cassi", "camera.cassi.dispersion=prism", "camera.cassi.prism_focal_length_mm=100",
                 "camera.sensor.pixel_pitch_um=10")
    bands = Bands.uniform(500, 700, 50)
    assert list(cam.shifts) == prism_dispersion(bands, "fused_silica", 30.0, 0.1, 10e-6)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("overrides, key, span", [
    (("camera.cassi.shift_px=1e30",), "camera.cassi.shift_px=1e+30", "over 4e+30 px"),
    (("camera.cassi.dispersion=prism", "camera.cassi.prism_focal_length_mm=1e30"),
     "camera.cassi.prism_focal_length_mm=1e+30", "prism"),
    (("camera.cassi.shift_px=1e308",), "camera.cassi.shift_px=1e+308", "over an infinite span"),
])
def test_an_absurd_dispersion_span_is_one_config_error_naming_its_key(kind, overrides, key, span):
    """The fuzz's shift_px=1e30 and prism_focal_length_mm=1e30 made the sensor 10^30 px wide: the shifts
    overflowed int64 (or the prism's rounding wrapped) as the camera was built. Now refused first."""
    with pytest.raises(ConfigError) as info:
        build_camera(cfg_of(kind, *overrides))
    msg = str(info.value)
    if span == "prism":  # f·tan((n(500 nm) − n(700 nm))·α) / pitch, f = 10^27 m, α = 30°, 6 µm pixels
        n = _fused_silica_n(np.array([500.0, 700.0]))
        span = f"over {1e27 * math.tan((n[0] - n[1]) * math.radians(30.0)) / 6e-6:.3g} px"
    assert "\n" not in msg and msg.startswith("camera.cassi.") and key in msg and span in msg, msg


@pytest.mark.parametrize("kind", KINDS)
def test_the_dispersion_bound_is_the_sensor_of_the_runs_scenes_in_the_budget(kind, monkeypatch):
    """S × (S + D) px at CASSI_BYTES_PER_SENSOR_PX bytes must fit the budget, S = data.synthetic_size
    (256 by default, the largest of it and data.patch_px): at 2 MiB D = 36 px fits and 37 does not; with
    128 px scenes 37 fits."""
    from hsicam.cameras.cassi import CASSI_BYTES_PER_SENSOR_PX

    monkeypatch.setenv("HSICAM_MEMORY_BUDGET_MB", "2")
    assert CASSI_BYTES_PER_SENSOR_PX * 256 * (256 + 36) <= 2 * 2**20 < CASSI_BYTES_PER_SENSOR_PX * 256 * (256 + 37)
    assert build_camera(cfg_of(kind, "camera.cassi.shift_px=9")).span == 36  # 5 bands: D = 4 · shift_px
    with pytest.raises(ConfigError, match=r"^camera.cassi.shift_px=9.25 px per band over 5 bands disperses the bands "
                                          r"over 37 px: the sensor of a 256 px scene .* more than the memory budget "
                                          r"of 2 MiB \(HSICAM_MEMORY_BUDGET_MB\); set camera.cassi.shift_px"):
        build_camera(cfg_of(kind, "camera.cassi.shift_px=9.25"))
    assert build_camera(cfg_of(kind, "camera.cassi.shift_px=9.25", "data.synthetic_size=128")).span == 37


# --------------------------------------------------------------------------------------------
# Config, factory, noise, errors
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("override, match", [
    ("camera.cassi.mask_density=0", "mask_density"),
    ("camera.cassi.mask_density=1.5", "mask_density"),
    ("camera.cassi.prism_apex_deg=90", "prism_apex_deg"),
    ("camera.cassi.prism_focal_length_mm=-1", "prism_focal_length_mm"),
    ("camera.cassi.convention=median", "convention"),
    ("camera.cassi.dispersion=grating", "dispersion"),
    ("camera.cassi.mask_file=mask.png", "npy"),
    ("camera.cassi.shift_px=0", "shift_px"),
])
def test_bad_cassi_config(override, match):
    with pytest.raises(ConfigError, match=match):
        cfg_of("dd_cassi", override)


def test_build_camera_kinds():
    assert isinstance(camera("dd_cassi"), DDCASSICamera)
    assert isinstance(camera("sd_cassi"), SDCASSICamera)
    assert isinstance(camera("dd_cassi").aperture, CodedAperture)


def test_sensor_noise_and_set_noise():
    cam = camera("dd_cassi", "camera.sensor.sigma=0.01")
    x = torch.rand(1, 5, 32, 32, dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    diff = cam(x, g) - cam.A(x)
    assert 0.008 < float(diff.std()) < 0.012
    cam.set_noise(sensor_sigma=0.0)
    assert cam.noise_levels() == {"sensor_sigma": 0.0}
    torch.testing.assert_close(cam(x), cam.A(x))


def test_bad_inputs():
    cam = camera("dd_cassi")
    with pytest.raises(InputError, match="bands"):
        cam.A(torch.rand(1, 4, 8, 8))
    with pytest.raises(InputError, match="B, C, H, W"):
        cam.A(torch.rand(5, 8, 8))
    with pytest.raises(InputError, match="B, 1, H, W"):
        cam.A_adjoint(torch.rand(1, 2, 8, 8))
    sd = camera("sd_cassi")
    with pytest.raises(InputError, match="not wider"):
        sd.A_adjoint(torch.rand(1, 1, 8, 8))


@pytest.mark.parametrize("kind", ["unrolled", "rdn"])
def test_a_capture_narrower_than_the_dispersion_is_one_input_error(kind):
    """An SD-CASSI capture narrower than the span reached torch as a negative tensor size (RuntimeError) through
    the networks' back-projection start; only a width equal to the span was refused."""
    extra = ["model.unrolled.prior_features=8", "model.unrolled.prior_blocks=1"] if kind == "unrolled" else \
        ["model.rdn.backprojection_input=true"]
    model = CameraSystem.from_config(load_config("tiny", ["camera.kind=sd_cassi", f"model.kind={kind}", *extra])).eval()
    span = model.camera.span
    for width in (span - 3, span):
        with torch.no_grad(), pytest.raises(InputError, match=f"width {width} is not wider than the dispersion span"):
            model.reconstruct(torch.rand(1, 1, 5, width))


def test_camera_system_with_cassi_has_no_weights_beyond_the_network():
    model = CameraSystem.from_config(load_config("tiny", ["camera.kind=dd_cassi"]))
    assert all(k.startswith("net.") for k in model.state_dict())
    x = torch.rand(2, 7, 20, 20)
    recon, sensor = model(x)
    assert sensor.shape == (2, 1, 20, 20) and recon.shape == model.target(x).shape == x.shape


# --------------------------------------------------------------------------------------------
# Training sees the whole aperture, and the RDN sees the code
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", KINDS)
def test_training_images_each_patch_through_a_random_window_of_the_aperture(kind):
    """In training mode the patch lands at a random place on the coded aperture: its measurement is
    the crop of a larger scene's measurement (the patch pasted at the drawn offset, by the loop
    reference), and the returned operator reproduces it. In eval mode the window is the top-left one."""
    cam = camera(kind)
    x = torch.rand(1, 5, 12, 10, dtype=torch.float64)
    cam.eval()
    y0, op0 = cam.measure(x)
    torch.testing.assert_close(y0, cam.A(x))
    cam.train()
    offsets = set()
    for seed in range(6):
        y, op = cam.measure(x, torch.Generator().manual_seed(seed))
        r0, c0 = op.offset
        offsets.add((r0, c0))
        torch.testing.assert_close(op.A(x), y)
        big = np.zeros((1, 5, r0 + 12, c0 + 10))
        big[..., r0:, c0:] = x.numpy()
        shifts, scale = list(cam.shifts), cam.scale
        if kind == "dd_cassi":
            ref = dd_reference(big, cam.aperture.pattern(r0 + 12, c0 + 10 + cam.span, dtype=torch.float64).numpy(), shifts, scale)
            ref = ref[..., r0:, c0:]
        else:
            ref = sd_reference(big, cam.aperture.pattern(r0 + 12, c0 + 10, dtype=torch.float64).numpy(), shifts, scale)
            ref = ref[..., r0:, c0:]
        np.testing.assert_allclose(y.numpy(), ref, rtol=1e-12, atol=1e-14)
    assert len(offsets) == 6  # six draws, six windows (out of ~500² places)
    # the adjoint of the shifted operator is exact too
    v = torch.rand_like(y)
    lhs, rhs = (op.A(x) * v).sum(), (x * op.A_adjoint(v)).sum()
    assert abs(float(lhs - rhs)) <= 1e-12 * float(lhs.abs())


def test_training_windows_stay_inside_a_file_aperture(tmp_path):
    arr = (np.arange(20 * 30).reshape(20, 30) % 3 == 0).astype(np.float64)
    np.save(tmp_path / "mask.npy", arr)
    cam = camera("dd_cassi", f"camera.cassi.mask_file={tmp_path / 'mask.npy'}").train()
    x = torch.rand(1, 5, 16, 16, dtype=torch.float64)
    for seed in range(20):
        _, op = cam.measure(x, torch.Generator().manual_seed(seed))
        assert 0 <= op.offset[0] <= 20 - 16 and 0 <= op.offset[1] <= 30 - 16 - cam.span


def test_rdn_with_backprojection_input_starts_from_the_code_aware_estimate():
    """The CASSI RDN reads Aᵀy ⊘ AᵀA𝟙: in each band the measurement scaled by C over the number of
    bands the pixel's code lets through, where the band is let through, else 0. Untrained, it
    returns that estimate's mean over bands in every band."""
    cfg = load_config("dd_cassi_rdn", ["model.rdn.backprojection_input=true"])
    model = CameraSystem.from_config(cfg).eval()
    assert model.net.tentative.in_channels == len(model.bands)
    x = torch.rand(1, len(model.bands), 24, 20)
    with torch.no_grad():
        recon, y = model(x)
    masks = model.camera.band_masks(24, 20).numpy()  # (C, H, W), binary
    n_open = masks.sum(axis=0)
    ref = np.where(masks > 0, y[0].numpy() * len(model.bands) / np.maximum(n_open, 1), 0.0)
    with torch.no_grad():
        seen = model.net.network_input(y, model.camera)
    np.testing.assert_allclose(seen[0].numpy(), ref, rtol=1e-5, atol=1e-6)
    flat = np.broadcast_to(ref.mean(axis=0, keepdims=True), ref.shape)
    np.testing.assert_allclose(recon[0].numpy(), flat, rtol=1e-5, atol=1e-6)
    # the paper's RDN reads the measurement alone (the preset's default)
    blind = CameraSystem.from_config(load_config("dd_cassi_rdn"))
    assert blind.net.tentative.in_channels == 1


def test_rdn_inputs_are_alternatives():
    with pytest.raises(ConfigError, match="alternatives"):
        load_config("dd_cassi_rdn", ["model.rdn.demosaic_input=true", "model.rdn.backprojection_input=true"])


# --------------------------------------------------------------------------------------------
# Property-based: any geometry
# --------------------------------------------------------------------------------------------
@settings(max_examples=25, deadline=None)
@given(kind=st.sampled_from(KINDS), convention=st.sampled_from(CONVENTIONS), c=st.integers(1, 5),
       h=st.integers(1, 6), w=st.integers(1, 7), shift=st.floats(0.6, 3.4), seed=st.integers(0, 2**31 - 1),
       density=st.floats(0.05, 1.0))
def test_any_geometry_matches_the_reference_and_is_adjoint(kind, convention, c, h, w, shift, seed, density):
    bands = Bands.uniform(500, 500 + 10 * (c - 1), 10) if c > 1 else Bands.from_centers([500.0])
    shifts = [round(shift * k) for k in range(c)]
    cls = DDCASSICamera if kind == "dd_cassi" else SDCASSICamera
    cam = cls(bands, CodedAperture(seed, density), shifts, convention=convention)
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(1, c, h, w, generator=g, dtype=torch.float64)
    scale = 1 / c if convention == "mean" else 1.0
    if kind == "dd_cassi":
        ref = dd_reference(x.numpy(), cam.aperture.pattern(h, w + max(shifts), dtype=torch.float64).numpy(), shifts, scale)
    else:
        ref = sd_reference(x.numpy(), cam.aperture.pattern(h, w, dtype=torch.float64).numpy(), shifts, scale)
    ax = cam.A(x)
    np.testing.assert_allclose(ax.numpy(), ref, rtol=1e-12, atol=1e-14)
    y = torch.rand(ax.shape, generator=g, dtype=torch.float64)
    lhs, rhs = float((ax * y).sum()), float((x * cam.A_adjoint(y)).sum())
    assert abs(lhs - rhs) <= 1e-9 * max(abs(lhs), 1e-12) + 1e-12


def test_an_rdn_reading_the_wider_sd_cassi_sensor_is_refused_and_its_back_projection_trains():
    """SD-CASSI's sensor is wider than its scene: an RDN reading g returned a sensor-sized cube and
    training failed at its first loss with a tensor-size traceback; now the config is refused, naming
    the setting that works, and that setting (the back-projection input) builds a scene-sized cube."""
    with pytest.raises(ConfigError, match=r"model.kind=rdn reading the sensor image returns a cube of the sensor's "
                                          r"size, but SDCASSICamera's sensor is larger than its scene .*set "
                                          r"model.rdn.backprojection_input=true"):
        CameraSystem.from_config(load_config("tiny", ["camera.kind=sd_cassi"]))
    system = CameraSystem.from_config(load_config("tiny", ["camera.kind=sd_cassi", "model.rdn.backprojection_input=true",
                                                           "model.consistency.iterations=0"]))
    scene = torch.rand(1, len(system.bands), 20, 24)
    with torch.no_grad():
        sensor = system.camera.A(scene)
        cube = system.reconstruct(sensor)
    assert sensor.shape[-1] > scene.shape[-1] and cube.shape == scene.shape
    # the DD-CASSI camera (sensor on the scene's grid) still takes the RDN reading g
    CameraSystem.from_config(load_config("tiny", ["camera.kind=dd_cassi"]))


# --------------------------------------------------------------------------------------------
# Guards found by mutation testing: ‖A‖² of an open aperture (power iteration), the tiling reach, and
# diag(ΦΦᵀ) of a window (loop sums over the aperture, tests/cassi_reference.py)
# --------------------------------------------------------------------------------------------
def power_iteration(op, shape, iterations: int = 200) -> float:
    """‖A‖² = the largest eigenvalue of AᵀA, by power iteration from a fixed random start (float64)."""
    g = torch.Generator().manual_seed(0)
    x = torch.rand(shape, generator=g, dtype=torch.float64)
    lam = 0.0
    for _ in range(iterations):
        x = op.A_adjoint(op.A(x))
        lam = float(x.norm())
        x = x / lam
    return lam


@pytest.mark.parametrize("kind", ("dd_cassi", "sd_cassi"))
@pytest.mark.parametrize("convention", ("sum", "mean"))
def test_cassi_lipschitz_is_the_operator_norm_squared_of_an_open_aperture(kind, convention):
    """With every aperture pixel open, ΦΦᵀ = s²·C·I, so ‖A‖² = s²·C exactly (power iteration on AᵀA): the
    snapshot's ``lipschitz`` is a bound of ‖A‖² that the unrolled network divides its steps by, and s·C (a
    dropped square) made the 'mean' convention's steps C = 5 times too small. (SD-CASSI: a scene at least as wide as
    the span D = 8 px, so that some sensor column sees every band.)"""
    cam = cassi(kind, "camera.cassi.mask_density=1", f"camera.cassi.convention={convention}")
    snap = cam.snapshot(nominal=True)
    ref = power_iteration(snap, (1, 5, 4, 12))
    assert snap.lipschitz == pytest.approx(ref, rel=1e-6)


def test_sd_cassi_reach_is_the_support_of_a_gradient_steps_impulse_response():
    """One gradient step x − αAᵀ(Ax − y) spreads a voxel over the support of AᵀA δ: for SD-CASSI, the voxel of
    band c at column j reaches sensor column j + d_c, which every band c′ reads back from its column j + d_c − d_c′,
    so the reach is the dispersion span D along the columns and 0 along the rows (the tiling halo, ``reach_px``)."""
    cam = cassi("sd_cassi", "camera.cassi.mask_density=1")
    snap = cam.snapshot(nominal=True)
    h, w = 5, 21
    rows, cols = 0, 0
    for c in range(5):
        x = torch.zeros(1, 5, h, w, dtype=torch.float64)
        x[0, c, h // 2, w // 2] = 1.0
        nz = torch.nonzero(snap.A_adjoint(snap.A(x))[0].abs().sum(0) > 0)
        rows = max(rows, int((nz[:, 0] - h // 2).abs().max()))
        cols = max(cols, int((nz[:, 1] - w // 2).abs().max()))
    assert cam.span == 8
    assert tuple(snap.reach_px) == (rows, cols) == (0, 8)


@pytest.mark.parametrize("kind", ("dd_cassi", "sd_cassi"))
@pytest.mark.parametrize("origin", ((0, 0), (3, 5)))
def test_cassi_gram_diagonal_of_a_window_is_the_loop_sum_over_its_aperture(kind, origin):
    """diag(ΦΦᵀ) of the sensor window at ``origin``, from the aperture array by the definitions: DD-CASSI
    s²·Σ_c P(r0 + i, c0 + j + d_c)², SD-CASSI s²·Σ_c P(r0 + i, c0 + j − d_c)² over the bands whose scene column
    j − d_c lies in the window. A diagonal taken at (0, 0) for every window fed the GAP steps of tiles the
    top-left code's normalisation."""
    cam = cassi(kind, "camera.cassi.convention=sum")
    snap = cam.snapshot(nominal=True)
    h, w = 6, 9
    ref = loop_gram_diagonal(cam, kind, h, w, origin)
    y = torch.zeros(1, 1, h, w, dtype=torch.float64)
    got = snap.gram_diagonal(y, origin)[0, 0].numpy()
    np.testing.assert_allclose(got, ref, atol=1e-12)


# --------------------------------------------------------------------------------------------
# ΦΦᵀ is diagonal and gram_diagonal is its diagonal, against the dense Φ (moved from
# models/test_solvers.py, whose GAP projection divides by it)
# --------------------------------------------------------------------------------------------
def dense_matrix(fn, n_in: int, in_shape, dtype=torch.float64) -> torch.Tensor:
    cols = []
    for k in range(n_in):
        e = torch.zeros(n_in, dtype=dtype)
        e[k] = 1
        cols.append(fn(e.reshape(in_shape)).reshape(-1))
    return torch.stack(cols, dim=1)


@pytest.mark.parametrize("kind", ("dd_cassi", "sd_cassi"))
@pytest.mark.parametrize("convention", ("sum", "mean"))
def test_phi_phi_t_is_diagonal_and_phi_diagonal_is_its_diagonal(kind, convention):
    cam = cassi_bands(kind, 4, f"camera.cassi.convention={convention}")
    h, w = 4, 5
    phi = dense_matrix(cam.A, 4 * h * w, (1, 4, h, w))  # (M, N)
    gram = phi @ phi.T
    off = gram - torch.diag(torch.diag(gram))
    assert float(off.abs().max()) == 0.0
    y = torch.zeros(1, 1, *cam.sensor_size((h, w)), dtype=torch.float64)
    d = cam.gram_diagonal(y).reshape(-1)
    expected = torch.diag(gram)
    expected = torch.where(expected > 1e-12, expected, torch.ones_like(expected))
    torch.testing.assert_close(d, expected)

@pytest.mark.parametrize("kind", ["sd_cassi", "dd_cassi"])
@pytest.mark.parametrize("convention", CONVENTIONS)
def test_white_peak_bounds_a_white_scenes_sensor_image(kind, convention):
    """``white_peak`` (what `reconstruct` takes as the range of the images a network of the camera trained on): no
    pixel of a white scene's image exceeds it, and it is reached where every band's code is open: 1 with ``mean``,
    the band count with ``sum`` (session 75's hunt: a sum-convention capture of peak 22.7 was called DN, and following the
    advice, --auto-level 1, took its reconstruction from 16.7 to 7.6 dB)."""
    cam = camera(kind, f"camera.cassi.convention={convention}")
    c = len(cam.bands)
    white = torch.ones(1, c, 40, 40, dtype=torch.float64)
    with torch.no_grad():
        image = cam.A(white)
    assert float(image.max()) <= cam.white_peak * (1 + 1e-9)
    assert float(image.max()) > 0.5 * cam.white_peak  # a random code: some pixel sees most bands open
    assert cam.white_peak == pytest.approx(1.0 if convention == "mean" else float(c))


def test_a_float_capture_within_a_sum_cameras_range_is_not_taken_for_dn(caplog):
    """The float capture's "holds DN?" warning compares with the range the network trained on (``trained_peak``)."""
    from hsicam.data.images import FLOAT_OVER_SCALE, RawCorrection, preprocess_raw

    raw = np.full((16, 16), 22.7, dtype=np.float32)
    with caplog.at_level(logging.WARNING):
        preprocess_raw(raw, 1.0, RawCorrection(), "cap", trained_peak=28.0)
    assert not [r for r in caplog.records if "holds DN" in r.getMessage()]
    with caplog.at_level(logging.WARNING):
        preprocess_raw(raw, 1.0, RawCorrection(), "cap")  # a DOE camera's range, [0, 1]
    said = [r.getMessage() for r in caplog.records if "holds DN" in r.getMessage()]
    assert len(said) == 1 and "within [0, 1]" in said[0] and 22.7 > FLOAT_OVER_SCALE
