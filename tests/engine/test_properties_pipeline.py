"""Property-based tests (hypothesis) of the least-squares linear map and its consistency step, tiled inference,
the CFA-offset estimate and the fabrication exports, on unusual inputs: 1-px and prime-sized images, images
smaller than the filter window, one band or many, non-uniform band grids, CFA periods 1-4 at every phase, tiles
that do not divide the image, float64 and non-contiguous tensors, extreme scales, 2-2^16 levels. Each invariant is
checked against an independent reference: a brute-force loop in numpy (least squares, the constrained optimum by
the null-space method, the camera's operator and the per-phase filters), the whole image, a batch item alone, the
file read back in its real format (safetensors, TIFF, CSV, GDSII by polygon area)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from hsicam.cameras.doe_camera import DOESnapshot
from hsicam.engine.inference import reconstruct_tiled
from hsicam.errors import InputError
from hsicam.export.cfa import fit_filter, read_transmission_csv, write_transmission_csv
from hsicam.export.doe import quantize_levels, read_height_csv, read_height_tiff, write_height_csv, write_height_tiff
from hsicam.models.consistency import linear_consistency_step, linear_reach_px
from hsicam.models.demosaic import LinearDemosaicFit
from hsicam.optics.doe import quantize_heights
from hsicam.runs.linear_step import linear_step_info, load_linear_step, save_linear_step, stale_reason
from hsicam.spectral import Bands

pytestmark = pytest.mark.usefixtures("one_torch_thread")

PROPS = settings(max_examples=40, deadline=None, derandomize=True, database=None,
                 suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
FEW = settings(PROPS, max_examples=15)


def _patches(g: np.ndarray, k: int) -> np.ndarray:
    """(B, H, W, K²): the K×K window around every pixel of g (B, 1, H, W), the image extended by replication."""
    r = k // 2
    gp = np.pad(g[:, 0], ((0, 0), (r, r), (r, r)), mode="edge")
    b, h, w = g.shape[0], g.shape[2], g.shape[3]
    out = np.empty((b, h, w, k * k))
    for i in range(h):
        for j in range(w):
            out[:, i, j] = gp[:, i : i + k, j : j + k].reshape(b, -1)
    return out


def _phase(h: int, w: int, m: int, origin: tuple[int, int]) -> np.ndarray:
    return ((np.arange(h)[:, None] + origin[0]) % m) * m + (np.arange(w)[None, :] + origin[1]) % m


def _normal_equations(g, t, m, k, origin, ridge):
    """Per phase: X_qᵀX_q + reg I and X_qᵀT_q from the definition (reg = ridge × mean diagonal)."""
    x = _patches(g, k)
    ph = np.broadcast_to(_phase(g.shape[2], g.shape[3], m, origin), x.shape[:3])
    vals = t.transpose(0, 2, 3, 1)
    grams, cross = [], []
    for q in range(m * m):
        xs, ts = x[ph == q], vals[ph == q]
        gram = xs.T @ xs
        grams.append(gram + ridge * np.trace(gram) / (k * k) * np.eye(k * k))
        cross.append(xs.T @ ts)
    return grams, cross


# ------------------------------------------------------------------------------------------------
# LinearDemosaicFit: the least-squares filters
# ------------------------------------------------------------------------------------------------
@PROPS
@given(m=st.integers(1, 3), k=st.sampled_from([1, 3, 5]), c=st.integers(1, 4), h=st.integers(1, 9),
       w=st.integers(1, 9), b=st.integers(1, 2), oy=st.integers(0, 5), ox=st.integers(0, 5), seed=st.integers(0, 999),
       scale=st.sampled_from([1e-6, 1.0, 1e4]))
def test_free_fit_is_the_ridge_least_squares_by_brute_force(m, k, c, h, w, b, oy, ox, seed, scale):
    """Per phase (w_q = (X_qᵀX_q + reg I)⁻¹ X_qᵀT_q, a phase without samples 0), for any image size (smaller
    than the window or the period too), origin, batch and brightness (the ridge is relative: scale-free)."""
    rng = np.random.default_rng(seed)
    g, t = rng.random((b, 1, h, w)) * scale, rng.random((b, c, h, w))
    fit = LinearDemosaicFit(m, c, k, ridge=1e-3)
    fit.add(torch.from_numpy(g), torch.from_numpy(t), (oy, ox))
    got = fit.solve().double().numpy()
    grams, cross = _normal_equations(g, t, m, k, (oy, ox), 1e-3)
    ref = np.stack([np.linalg.solve(gr, cr).T.reshape(c, k, k) if np.trace(gr) > 0 else np.zeros((c, k, k))
                    for gr, cr in zip(grams, cross)])
    np.testing.assert_allclose(got, ref, rtol=2e-4, atol=1e-5 * np.abs(ref).max())


@PROPS
@given(m=st.integers(1, 3), k=st.sampled_from([1, 3, 5]), c=st.integers(1, 3), h=st.integers(1, 9),
       w=st.integers(1, 9), b=st.integers(1, 2), oy=st.integers(0, 5), ox=st.integers(0, 5), seed=st.integers(0, 999),
       scale=st.sampled_from([1e-6, 1.0, 1e4]), ridge=st.sampled_from([1e-6, 1e-2]))
def test_flat_field_fit_is_the_constrained_optimum_by_the_null_space_method(m, k, c, h, w, b, oy, ox, seed, scale,
                                                                            ridge):
    """Under S_q w_q = S_0 w_0 for all phases q (S_q[p, tap] = 1 where phase q's tap reads a pixel of phase p,
    written here from the definition) the fit minimises Σ_q ‖X_q w_q − T_q‖² + reg_q ‖w_q‖²: w = Z z with Z a
    basis of the constraints' null space (SVD) and (ZᵀGZ) z = Zᵀc.

    Every phase has samples (h, w >= m, as on any training scene): a phase without any is a degenerate problem
    (its Gram matrix 0, an absolute ridge of 1 against a relative one elsewhere) that only a sub-period image makes."""
    assume(k >= m and h >= m and w >= m)
    rng = np.random.default_rng(seed)
    g, t = rng.random((b, 1, h, w)) * scale, rng.random((b, c, h, w))
    fit = LinearDemosaicFit(m, c, k, ridge=ridge, flat_field=True)
    fit.add(torch.from_numpy(g), torch.from_numpy(t), (oy, ox))
    got = fit.solve().double().numpy()
    q_n, n, r = m * m, k * k, k // 2
    select = np.zeros((q_n, q_n, n))
    for q in range(q_n):
        for u in range(k):
            for v in range(k):
                select[q, ((q // m + u - r) % m) * m + (q % m + v - r) % m, u * k + v] = 1.0
    cons = np.zeros(((q_n - 1) * q_n, q_n * n))
    for q in range(1, q_n):
        cons[(q - 1) * q_n : q * q_n, q * n : (q + 1) * n] = select[q]
        cons[(q - 1) * q_n : q * q_n, :n] = -select[0]
    if cons.size:
        _, sv, vt = np.linalg.svd(cons)
        null = vt[int((sv > 1e-9).sum()) :].T
    else:
        null = np.eye(q_n * n)
    grams, cross = _normal_equations(g, t, m, k, (oy, ox), ridge)
    big = np.zeros((q_n * n, q_n * n))
    for q in range(q_n):
        big[q * n : (q + 1) * n, q * n : (q + 1) * n] = grams[q]
    sol = null @ np.linalg.solve(null.T @ big @ null, null.T @ np.concatenate(cross))
    ref = sol.reshape(q_n, n, c).transpose(0, 2, 1).reshape(q_n, c, k, k)
    np.testing.assert_allclose(got, ref, rtol=1e-3, atol=1e-4 * np.abs(ref).max())


# ------------------------------------------------------------------------------------------------
# linear_step.safetensors: round trip
# ------------------------------------------------------------------------------------------------
@PROPS
@given(m=st.integers(1, 4), c=st.integers(1, 9), k=st.sampled_from([1, 3, 7]),
       layout=st.sampled_from(["float64", "float32", "transposed", "channels_last"]),
       window=st.sampled_from([1, 3, 7, 9]), seed=st.integers(0, 99))
def test_linear_step_file_round_trip(tmp_path_factory, m, c, k, layout, window, seed):
    """Any dtype or memory layout in, the float32 filters out (bit for bit), the metadata back with the stored
    width; another band count, period or filter width is named."""
    d = tmp_path_factory.mktemp("ls")
    g = torch.Generator().manual_seed(seed)
    ref = torch.randn(m * m, c, k, k, generator=g, dtype=torch.float64) * 10.0 ** float(seed % 7 - 3)
    weight = {"float64": ref, "float32": ref.float(),
              "transposed": ref.transpose(-1, -2).contiguous().transpose(-1, -2),
              "channels_last": ref.contiguous(memory_format=torch.channels_last)}[layout]
    weights = d / "model.safetensors"
    weights.write_bytes(bytes([seed]))
    from hsicam.runs.checkpoint import file_sha256

    info = {"window_px": k, "training_scenes": np.int64(seed), "ridge": np.float32(1e-6),
            "weights_sha256": file_sha256(weights)}
    save_linear_step(d / "ls.safetensors", weight, info)
    back = load_linear_step(d / "ls.safetensors", c, m)
    assert back.dtype == torch.float32 and torch.equal(back, ref.float())
    meta = linear_step_info(d / "ls.safetensors")
    assert meta["filter_px"] == k and meta["training_scenes"] == seed and meta["weights_sha256"] == file_sha256(weights)
    assert stale_reason(d / "ls.safetensors", weights, k) is None
    assert (stale_reason(d / "ls.safetensors", weights, window) is None) == (window == k)
    with pytest.raises(InputError, match=f"do not fit a camera of {c + 1} bands"):
        load_linear_step(d / "ls.safetensors", c + 1, m)
    weights.write_bytes(bytes([seed + 1]))
    assert "other weights" in stale_reason(d / "ls.safetensors", weights, k)


# ------------------------------------------------------------------------------------------------
# linear_consistency_step: the definition, batch items, tiles
# ------------------------------------------------------------------------------------------------
def _snapshot(bands: int, kernel: int, period: int, seed: int, dtype=torch.float64) -> DOESnapshot:
    g = torch.Generator().manual_seed(seed)
    psf = torch.rand(bands, kernel, kernel, generator=g, dtype=torch.float64)
    psf = psf / psf.sum(dim=(-2, -1), keepdim=True)
    tile = 0.05 + 0.95 * torch.rand(bands, period, period, generator=g, dtype=torch.float64)
    return DOESnapshot(Bands.uniform(400.0, 400.0 + 10.0 * (bands - 1), 10.0), psf.to(dtype), tile.to(dtype), period)


def _a_replicated(x, psf, tile, origin):
    """y_ij = Σ_c κ_c(i + oy, j + ox) Σ_uv p_c[u, v] x_c[i − u + r, j − v + r], x extended by replication."""
    b, c, h, w = x.shape
    k, m, r = psf.shape[-1], tile.shape[-1], psf.shape[-1] // 2
    rows, cols = np.clip(np.arange(-r, h + r), 0, h - 1), np.clip(np.arange(-r, w + r), 0, w - 1)
    xe = x[:, :, rows][:, :, :, cols]
    y = np.zeros((b, 1, h, w))
    for i in range(h):
        for j in range(w):
            win = xe[:, :, i : i + k, j : j + k][:, :, ::-1, ::-1]  # x[i − u + r]: the window flipped
            kappa = tile[:, (i + origin[0]) % m, (j + origin[1]) % m]
            y[:, 0, i, j] = np.einsum("bcuv,cuv,c->b", win, psf, kappa)
    return y


def _phase_linear(g, weight, origin):
    m, k = math.isqrt(weight.shape[0]), weight.shape[-1]
    x = _patches(g, k)
    ph = _phase(g.shape[2], g.shape[3], m, origin)
    return np.einsum("bhwn,hwcn->bchw", x, weight.reshape(m * m, weight.shape[1], k * k)[ph])


@PROPS
@given(bands=st.integers(1, 5), kernel=st.sampled_from([1, 3, 5]), m=st.integers(1, 4),
       window=st.sampled_from([1, 3, 5]), h=st.integers(1, 11), w=st.integers(1, 11),
       origin=st.tuples(st.integers(0, 9), st.integers(0, 9)), gain=st.sampled_from([0.1, 0.5, 1.0]),
       iterations=st.integers(0, 3), seed=st.integers(0, 99))
def test_linear_step_is_x_plus_gain_w_residual_by_brute_force(bands, kernel, m, window, h, w, origin, gain, iterations,
                                                              seed):
    """x ← x + gain · W(y − A x), the estimate extended by replication for A, each batch item as alone."""
    op = _snapshot(bands, kernel, m, seed)
    rng = np.random.default_rng(seed)
    x0 = rng.random((2, bands, h, w))
    y = rng.random((2, 1, h, w))
    weight = rng.normal(size=(m * m, bands, window, window)) * 0.1
    got = linear_consistency_step(op, torch.from_numpy(y), torch.from_numpy(x0), torch.from_numpy(weight), origin,
                                  gain=gain, iterations=iterations, psf_energy=1.0).numpy()
    x = x0
    for _ in range(iterations):
        x = x + gain * _phase_linear(y - _a_replicated(x, op.psf.numpy(), op.tile.numpy(), origin), weight, origin)
    np.testing.assert_allclose(got, x, rtol=1e-9, atol=1e-10)


@FEW
@given(bands=st.integers(1, 4), kernel=st.sampled_from([1, 3, 5]), m=st.integers(1, 4),
       window=st.sampled_from([1, 3, 5]), h=st.integers(1, 37), w=st.integers(1, 37),
       origin=st.tuples(st.integers(0, 9), st.integers(0, 9)),
       iterations=st.integers(1, 3), tile=st.integers(1, 37), extend=st.sampled_from([True, False, "reflect"]),
       seed=st.integers(0, 99))
def test_linear_step_tiles_with_its_declared_reach_equal_the_whole_image(bands, kernel, m, window, h, w, origin,
                                                                         iterations, tile, extend, seed):
    op = _snapshot(bands, kernel, m, seed)
    g = torch.Generator().manual_seed(seed + 3)
    x0 = torch.rand(1, bands, h, w, generator=g, dtype=torch.float64)
    y = torch.rand(1, 1, h, w, generator=g, dtype=torch.float64)
    weight = torch.randn(m * m, bands, window, window, generator=g, dtype=torch.float64) * 0.1
    kw = dict(gain=0.5, iterations=iterations, psf_energy=1.0, extend=extend)
    whole = linear_consistency_step(op, y, x0, weight, origin, **kw)

    def run(s, origin_=(0, 0)):
        part = x0[..., origin_[0] : origin_[0] + s.shape[-2], origin_[1] : origin_[1] + s.shape[-1]]
        return linear_consistency_step(op, s, part, weight, (origin[0] + origin_[0], origin[1] + origin_[1]), **kw)

    def run_o(s, origin=(0, 0)):
        return run(s, origin)

    tiled = reconstruct_tiled(run_o, y, tile_px=tile, halo_px=linear_reach_px(op, window, iterations, 1.0))
    torch.testing.assert_close(tiled, whole, rtol=1e-10, atol=1e-10)


@FEW
@given(iterations=st.integers(1, 2), window=st.sampled_from([3, 5, 9]), h=st.integers(5, 41), w=st.integers(5, 41),
       tile=st.integers(3, 40), seed=st.integers(0, 99))
def test_tiny_system_with_linear_steps_tiled_equals_whole(tiny_config, iterations, window, h, w, tile, seed):
    """The whole pipeline (network, then the linear step with the run's filters) of the tiny camera: tiles of
    any size with the system's declared context give the whole image."""
    model = _tiny_linear_system(tiny_config, iterations)
    m, c = model.camera.code_period, len(model.bands)
    model.linear_step = torch.randn(m * m, c, window, window, generator=torch.Generator().manual_seed(seed)) * 0.05
    sensor = torch.rand(1, 1, h, w, generator=torch.Generator().manual_seed(seed + 1))
    fn = model.reconstructor()
    with torch.no_grad():
        whole = fn(sensor)
        tiled = reconstruct_tiled(fn, sensor, tile_px=tile, halo_px=model.context_px)
    torch.testing.assert_close(tiled, whole, rtol=1e-4, atol=1e-5)


_SYSTEMS: dict = {}


def _tiny_linear_system(tiny_config, iterations):
    from hsicam.models import CameraSystem

    if iterations not in _SYSTEMS:
        cfg = tiny_config(f"model.consistency.iterations={iterations}", "model.consistency.kind=linear",
                          "model.consistency.window_px=5")
        torch.manual_seed(0)
        _SYSTEMS[iterations] = CameraSystem.from_config(cfg).eval()
    return _SYSTEMS[iterations]


_PRETRAINED: dict = {}


@pytest.mark.slow
@settings(PROPS, max_examples=4)
@given(dy=st.integers(0, 7), dx=st.integers(0, 7), seed=st.integers(0, 9))
def test_cfa_offset_of_a_crop_of_a_simulated_capture_comes_back(dy, dx, seed):
    """pretrained:standard (4×4 CFA), a noise-free capture of a procedural scene cropped at (dy, dx): the estimate is
    (dy mod 4, dx mod 4), the smallest residual. Windows of 96 px: at 64 px (34 px scored inside the PSF margin) a
    wrong phase can win by a few percent and is not flagged ambiguous: below the 128-256 px the module measured."""
    from procedural_scenes import procedural_scene

    from hsicam.engine.cfa_offset import estimate_cfa_offset
    from hsicam.runs.folder import load_run

    if "system" not in _PRETRAINED:
        _PRETRAINED["system"] = load_run("pretrained:standard", overrides=("camera.boundary=same",))[1].eval()
    system = _PRETRAINED["system"]
    scene = torch.from_numpy(procedural_scene(system.camera.bands.centers_nm, size=110, seed=seed))[None]
    with torch.no_grad():
        sensor = system.camera.A(scene)
    est = estimate_cfa_offset(system, sensor[..., dy:, dx:], window_px=96)
    assert est.offset == (dy % 4, dx % 4), est.residuals
    assert est.residuals[f"{dy % 4},{dx % 4}"] == min(est.residuals.values())


# ------------------------------------------------------------------------------------------------
# DOE export: L-level quantisation and the files
# ------------------------------------------------------------------------------------------------
@PROPS
@given(k=st.integers(1, 16), wrap=st.booleans(), top_nm=st.floats(1.0, 1e5), n=st.integers(1, 9),
       span=st.floats(0.0, 3.0), seed=st.integers(0, 999))
def test_quantized_levels_are_within_half_a_level_and_the_trainings_rule(k, wrap, top_nm, n, span, seed):
    """L = 2^k levels: index in [0, L), height index·top/L; within half a step of the height modulo top (wrap)
    or of the height clamped to [0, (L−1)·top/L]; the same indices as training's torch rule (float64)."""
    levels = 2**k
    top = top_nm * 1e-9
    h = np.random.default_rng(seed).random((n, n)) * span * top
    idx, hq = quantize_levels(h, levels, top, wrap)
    step = top / levels
    assert idx.min() >= 0 and idx.max() <= levels - 1
    np.testing.assert_allclose(hq, idx * step, rtol=0, atol=1e-12 * top)
    if wrap:
        err = np.mod(hq - h + top / 2, top) - top / 2
    else:
        err = hq - np.clip(h, 0, (levels - 1) * step)
    assert np.abs(err).max() <= step / 2 * (1 + 1e-9)
    torch_q = quantize_heights(torch.from_numpy(h), levels, top, wrap=wrap).numpy()
    np.testing.assert_allclose(torch_q, hq, rtol=0, atol=1e-9 * step)


@PROPS
@given(k=st.integers(1, 16), top_nm=st.floats(1.0, 1e5), n=st.integers(1, 9), cell_um=st.floats(0.5, 200.0),
       seed=st.integers(0, 999))
def test_height_files_read_back(tmp_path_factory, k, top_nm, n, cell_um, seed):
    """The 16-bit TIFF reads back within half its scale of each height and every level as itself; the CSV reads
    back the float32 heights and aperture exactly, with each cell's centre."""
    import csv

    d = tmp_path_factory.mktemp("h")
    levels = 2**k
    rng = np.random.default_rng(seed)
    h = rng.random((n, n)) * top_nm * 1e-9
    idx, hq = quantize_levels(h, levels, top_nm * 1e-9, True)
    aperture = (rng.random((n, n)) > 0.3) * rng.random((n, n))
    h_nm, hq_nm = (h * 1e9).astype(np.float32), (hq * 1e9).astype(np.float32)
    scale = write_height_tiff(d / "h.tif", h_nm, cell_um, {})
    back, desc = read_height_tiff(d / "h.tif")
    assert desc["scale_nm_per_count"] == scale and desc["cell_size_um"] == cell_um
    assert np.abs(back - h_nm).max() <= scale / 2 * (1 + 1e-6)
    step = top_nm / levels
    write_height_tiff(d / "q.tif", hq_nm, cell_um, {}, step_nm=step)
    back_q, _ = read_height_tiff(d / "q.tif")
    np.testing.assert_array_equal(np.round(back_q / step).astype(np.int64), idx)
    write_height_csv(d / "q.csv", hq_nm, aperture, cell_um, idx)
    h_back, a_back = read_height_csv(d / "q.csv", n)
    inside = aperture > 0
    np.testing.assert_array_equal(h_back, np.where(inside, hq_nm, 0))
    np.testing.assert_array_equal(a_back, np.where(inside, aperture.astype(np.float32), 0))
    with open(d / "q.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == int(inside.sum())
    for rec in rows:
        i, j = int(rec["row"]), int(rec["col"])
        assert int(rec["level"]) == idx[i, j]
        assert np.float32(float(rec["x_um"])) == np.float32((j - (n - 1) / 2) * cell_um)
        assert np.float32(float(rec["y_um"])) == np.float32(-(i - (n - 1) / 2) * cell_um)


@FEW
@given(k=st.integers(1, 4), n=st.integers(1, 12), cell_um=st.sampled_from([30.0, 7.0, 0.5, 12.3455, 1.0005, 250.0]),
       seed=st.integers(0, 999))
def test_gds_masks_cover_exactly_the_cells_of_each_bit(tmp_path_factory, k, n, cell_um, seed):
    """Layer j + 1's polygons cover, by area and without overlap, exactly the aperture's cells whose etch count
    L − 1 − level has bit j set: each cell (its square on the 1 nm grid) in or out whole."""
    gdstk = pytest.importorskip("gdstk")
    from hsicam.export.gds import cell_edges_um, write_gds

    levels = 2**k
    rng = np.random.default_rng(seed)
    level = rng.integers(0, levels, (n, n))
    aperture = (rng.random((n, n)) > 0.2).astype(float)
    path = tmp_path_factory.mktemp("g") / "d.gds"
    write_gds(path, level, levels, cell_um, aperture, 10.0, n * cell_um / 2)
    cell = {c.name: c for c in gdstk.read_gds(str(path)).cells}["DOE"]
    edges = cell_edges_um(n, cell_um)
    for j in range(k):
        want = (((levels - 1 - level) >> j) & 1).astype(bool) & (aperture > 0)
        polys = [p for p in cell.polygons if p.layer == j + 1]
        assert math.isclose(sum(p.area() for p in polys), float(sum(
            (edges[b + 1] - edges[b]) * (edges[a + 1] - edges[a]) for a, b in zip(*np.nonzero(want)))),
            rel_tol=1e-9, abs_tol=1e-9)
        for i in range(n):
            for jj in range(n):  # each cell: inside its polygons by area (the union of the cell and the masks)
                sq = gdstk.rectangle((edges[jj], -edges[i + 1]), (edges[jj + 1], -edges[i]))
                common = gdstk.boolean(sq, polys, "and", precision=1e-4) if polys else []
                area = sum(p.area() for p in common)
                assert math.isclose(area, sq.area() if want[i, jj] else 0.0, abs_tol=1e-6 * sq.area()), (j, i, jj)


# ------------------------------------------------------------------------------------------------
# CFA export
# ------------------------------------------------------------------------------------------------
@PROPS
@given(c=st.integers(1, 12), m=st.integers(1, 4), seed=st.integers(0, 999), uniform=st.booleans())
def test_transmission_table_reads_back_and_every_filter_is_fitted(tmp_path_factory, c, m, seed, uniform):
    """On any band grid (one band, non-uniform steps): the CSV reads back the float32 tile exactly (and its
    peak-normalised version has maximum 1 per filter); each filter gets a fit within its bounds."""
    rng = np.random.default_rng(seed)
    centres = 400 + (np.arange(c) * 25.0 if uniform else np.cumsum(rng.uniform(0.5, 60, c)))
    bands = Bands(centres, np.full(c, 10.0))
    tile = rng.random((c, m, m)).astype(np.float32)
    tile /= tile.sum(0, keepdims=True)
    d = tmp_path_factory.mktemp("cfa")
    write_transmission_csv(d / "t.csv", tile, bands)
    write_transmission_csv(d / "p.csv", tile, bands, peak_normalised=True)
    lam, vals, names = read_transmission_csv(d / "t.csv")
    np.testing.assert_allclose(lam, centres, rtol=1e-11)  # written with 12 significant digits (%.12g)
    np.testing.assert_array_equal(vals, tile.reshape(c, m * m))
    assert names == [f"r{i}c{j}" for i in range(m) for j in range(m)]
    _, peak, _ = read_transmission_csv(d / "p.csv")
    np.testing.assert_allclose(peak.max(0), 1.0, rtol=1e-6)
    for curve in vals.T:
        f = fit_filter(lam, curve)
        assert f["rms_error"] <= 1.0 and math.isfinite(f["rms_error"])
        assert all(centres[0] - 1e3 <= g["centre_nm"] <= centres[-1] + 1e3 and g["fwhm_nm"] > 0
                   for g in f["components"])


def test_cfa_export_of_a_one_band_camera(tiny_config, tmp_path):
    """A camera of one band (bands.start_nm = stop_nm) has a CFA of all ones: its export fitted the flat curve
    with a Gaussian whose width bounds were crossed (lower 4.2 > upper 0.85 nm: scipy's ValueError 'Each lower
    bound must be strictly less than each upper bound'); now the curve (1 at the band) is fitted."""
    from hsicam.cameras import DOECamera
    from hsicam.export.cfa import export_cfa

    cam = DOECamera.from_config(tiny_config("bands.start_nm=550", "bands.stop_nm=550"))
    info = export_cfa(cam, tmp_path)
    lam, vals, _ = read_transmission_csv(tmp_path / "cfa_transmission.csv")
    np.testing.assert_array_equal(lam, [550.0])
    np.testing.assert_array_equal(vals, np.ones((1, cam.code_period**2), np.float32))
    assert info["filters"] == cam.code_period**2 and info["fit_rms_error"]["max"] < 1e-6
