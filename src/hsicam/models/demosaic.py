"""Network-free per-band estimates of a sensor image (the start of the learned networks).

The demosaic of a CFA camera's image:

    x̃_c = box_w(κ_c ⊙ g) / box_w(κ_c)

a ``w``×``w`` box (odd; zero outside the image): the average of g over the neighbourhood, weighted
by how much each pixel's filter transmits band c. With selective filters it is a crude spectral
estimate; the demo reports it as the reference a network must beat. ``kernel="tent"`` weighs the
neighbourhood by a separable triangle instead (1, 2, …, r+1, …, 2, 1 for w = 2r + 1): with
w = 2m − 1 for a CFA of period m it is the weighted-bilinear MSFA demosaic (each filter's samples
interpolated bilinearly between the lattice points, then mixed by κ_c), which places every
filter's samples symmetrically about the pixel, where an odd box over an even period counts some
filters twice.

The back-projection Aᵀy ⊘ AᵀA𝟙 of any camera (the CASSI networks' start: which bands each
pixel's code lets through, on the scale of the cube).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


#: Neighbourhood weights of :func:`demosaic`.
DEMOSAIC_KERNELS = ("box", "tent")


def demosaic(sensor: torch.Tensor, code: torch.Tensor, window: int, kernel: str = "box") -> torch.Tensor:
    """Per-band normalised local average of the coded sensor image (no learning).

    Args:
        sensor: g, (B, 1, H, W).
        code: κ, (C, H, W) (the CFA over the same pixels).
        window: odd width of the neighbourhood in pixels.
        kernel: "box" (flat weights) or "tent" (separable triangle, see the module docstring).
    Returns:
        (B, C, H, W).
    """
    if kernel not in DEMOSAIC_KERNELS:
        raise ValueError(f"demosaic kernel must be one of {', '.join(DEMOSAIC_KERNELS)}, got {kernel!r}")
    if window <= 1:
        return sensor * code.unsqueeze(0) / code.clamp_min(1e-6).unsqueeze(0)
    mean = box_mean if kernel == "box" else tent_mean
    num = mean(sensor * code.unsqueeze(0), window)
    den = mean(code.unsqueeze(0), window)
    return num / den.clamp_min(1e-6)


def tent_mean(x: torch.Tensor, window: int) -> torch.Tensor:
    """Weighted mean over a ``window``×``window`` separable triangle (odd ``window`` = 2r + 1,
    weights 1, 2, …, r + 1, …, 2, 1 per axis, normalised; zeros outside): (B, C, H, W)."""
    r = window // 2
    w = (r + 1 - torch.arange(-r, r + 1, device=x.device).abs()).to(x.dtype)
    w = w / w.sum()
    c = x.shape[1]
    x = F.conv2d(x, w.view(1, 1, 1, -1).expand(c, 1, 1, -1), padding=(0, r), groups=c)
    return F.conv2d(x, w.view(1, 1, -1, 1).expand(c, 1, -1, 1), padding=(r, 0), groups=c)


def box_mean(x: torch.Tensor, window: int) -> torch.Tensor:
    """Mean over a ``window``×``window`` box (zeros outside), as two 1-D passes: (B, C, H, W)."""
    r = window // 2
    x = F.avg_pool2d(x, (1, window), stride=1, padding=(0, r))
    return F.avg_pool2d(x, (window, 1), stride=1, padding=(r, 0))


def brightness(sensor: torch.Tensor, window: int, eps: float) -> torch.Tensor:
    """Local brightness b = box_w(g) + ε, (B, 1, H, W) → (B, 1, H, W), in sensor units.

    The networks see g / b and return b × their output, so a scene and the same scene ×c get
    the same reconstruction ×c (for b ≫ ε): what is learned on bright patches serves dark ones.
    Since Σ_c κ_c = 1 per pixel, g is a weighted mean over bands and b is on the scale of the cube.
    The box mean is taken at 0 where it is negative (a dark area of a capture whose black level was set a little
    high): b at or below 0 made g / b infinite, and the whole cube NaN once the convolutions spread it.
    """
    return box_mean(sensor, window).clamp_min(0.0) + eps


def skip_window(period: int, kernel: str = "box") -> int:
    """Default width (px, odd) of :func:`demosaic` for a CFA of ``period`` m: m rounded up to odd
    (box), 2m − 1 (tent: the weighted-bilinear demosaic)."""
    period = int(period)
    if kernel == "tent":
        return 2 * period - 1
    return period if period % 2 else period + 1


def demosaic_window(camera) -> int:
    """Odd box width for ``camera``: its code period (the CFA's m), rounded up to odd."""
    return skip_window(getattr(camera, "code_period", 1))


def camera_demosaic(camera, sensor: torch.Tensor, origin: tuple[int, int] = (0, 0), kernel: str = "box",
                    window: int | None = None) -> torch.Tensor:
    """:func:`demosaic` of ``sensor`` (B, 1, H, W) with ``camera``'s sensor code at ``origin``.

    ``window`` None: a box of :func:`demosaic_window`, or (``kernel="tent"``) the weighted-bilinear
    tent of 2m − 1 px for a CFA of period m. Raises ``NotImplementedError`` for cameras without a
    per-band sensor code (CASSI).
    """
    code = camera.sensor_code(sensor.shape[-2], sensor.shape[-1], origin).to(sensor.dtype)
    if window is None:
        window = skip_window(getattr(camera, "code_period", 1), kernel)
    return demosaic(sensor, code, window, kernel)


def camera_operator(camera):
    """The frozen operator a network uses: ``camera.snapshot(nominal=True)``, or ``camera`` itself
    when it already is one (e.g. the snapshot that made the measurement)."""
    snap = getattr(camera, "snapshot", None)
    return snap(nominal=True) if callable(snap) else camera


def backprojection(op, y: torch.Tensor, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
    """Aᵀy ⊘ AᵀA𝟙: for a pixel-wise (CASSI) operator each coded voxel's share of its measurement."""
    b, _, h, w = y.shape
    ones = y.new_ones(1, len(op.bands), *op.scene_size((h, w)))
    norm = op.A_adjoint(op.A(ones, origin), origin)
    eps = 1e-6 * (getattr(op, "lipschitz", None) or 1.0)  # position-independent, so tiles = whole
    return op.A_adjoint(y, origin) / norm.clamp_min(eps)


# ---------------------------------------------------------------------------------------------
# The best linear reconstruction of a CFA camera: a K×K filter per CFA phase and band
# ---------------------------------------------------------------------------------------------
#
# A periodic CFA makes the sensor image cyclo-stationary: every pixel of CFA phase p = (i mod m,
# j mod m) sees the same filter, so the best *linear* estimate of the cube from a K×K neighbourhood
# of g is one K×K filter per phase and band,
#
#     x̂_c(i, j) = Σ_{|u|,|v| ≤ K//2} W[p(i, j), c, u, v] · g(i + u, j + v),
#
# the linear minimum-mean-square-error (LMMSE) demosaic: fitted by least squares on training
# scenes imaged through the camera, it undoes the optics' blur and the mosaic's sampling together,
# as far as a linear map can (the tent demosaic is one such map, fixed). No offset term: a scene
# ×c gives the estimate ×c.
#
# Flat-field constraint (``flat_field=True``): a spatially uniform scene gives an m-periodic sensor
# image, and the unconstrained fit answers it with an estimate that differs between phases — a
# faint m×m trace on flat areas (visible on the demo's line-spectrum scene). With the constraint,
# every phase's filter responds to any m-periodic image with the same spectrum,
#
#     M_q = S_q w_q = M   for every phase q,   S_q[p, tap] = 1 where the tap falls on phase p,
#
# so flat stays flat. Exact least squares under it: per phase w_q = G_q⁻¹(c_q − S_qᵀλ_q), with
# λ_q = H_q⁻¹(S_q G_q⁻¹ c_q − M), H_q = S_q G_q⁻¹ S_qᵀ and M = (Σ H_q⁻¹)⁻¹ Σ H_q⁻¹ S_q G_q⁻¹ c_q
# (the Lagrange conditions; only m²×m² systems besides each phase's own Gram matrix). On the demo's
# camera: the trace's share of the error energy on that scene 5.1 % → 2.0 % (+0.7 dB there), the
# validation mean +0.05 dB / +0.002 SSIM, held out +0.01 dB / +0.001 (docs/networks_log.md).


def phase_linear(sensor: torch.Tensor, weight: torch.Tensor, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
    """Apply per-phase filters: ``sensor`` (B, 1, H, W) of the window at ``origin``, ``weight``
    (m², C, K, K) (phase index a·m + b for pixel rows ≡ a, columns ≡ b mod m on the whole sensor;
    K odd) → (B, C, H, W). The image is extended by replication beyond its border, so a tile with
    a halo of K // 2 px equals the whole image (each output pixel reads the K×K pixels around it)."""
    if sensor.dim() != 4 or sensor.shape[1] != 1:
        raise ValueError(f"sensor image must be (B, 1, H, W), got shape {tuple(sensor.shape)}")
    phases, bands, k, _ = weight.shape
    m = math.isqrt(phases)
    if m * m != phases or k % 2 == 0:
        raise ValueError(f"weight must be (m², C, K, K) with K odd, got shape {tuple(weight.shape)}")
    b, _, h, w = sensor.shape
    r = k // 2
    padded = F.pad(sensor, (r, r, r, r), mode="replicate") if r else sensor
    out = sensor.new_empty(b, bands, h, w)
    weight = weight.to(sensor.dtype)
    for row_phase in range(m):
        i0 = (row_phase - origin[0]) % m  # the window's first row of this phase
        for col_phase in range(m):
            j0 = (col_phase - origin[1]) % m
            if i0 >= h or j0 >= w:
                continue
            rows, cols = len(range(i0, h, m)), len(range(j0, w, m))
            sub = padded[:, 0, i0 : i0 + (rows - 1) * m + k, j0 : j0 + (cols - 1) * m + k]
            patches = sub.unfold(1, k, m).unfold(2, k, m).reshape(b, rows * cols, k * k)  # a view, then one copy
            est = patches @ weight[row_phase * m + col_phase].reshape(bands, k * k).T  # (B, rows·cols, C)
            out[:, :, i0::m, j0::m] = est.transpose(1, 2).reshape(b, bands, rows, cols)
    return out


class LinearDemosaicFit:
    """Least-squares fit of :func:`phase_linear`'s filters from (sensor, truth) pairs.

    ``add(sensor, truth)`` accumulates the normal equations per phase (float64; ``sensor``
    (B, 1, H, W) at ``origin``, ``truth`` (B, C, H, W) on the same pixels); ``solve()`` returns
    the weights (m², C, K, K) with a ridge of ``ridge`` × the mean diagonal of each phase's Gram
    matrix (a phase without samples gets zeros in the free fit). ``flat_field``: least squares under the flat-field
    constraint above (every phase answers an m-periodic image with the same spectrum; needs a window
    of at least one period)."""

    def __init__(self, period: int, bands: int, window: int, ridge: float = 1e-6, flat_field: bool = False) -> None:
        if period < 1 or window < 1 or window % 2 == 0:
            raise ValueError(f"period must be >= 1 and window odd, got {period} and {window}")
        if not (ridge >= 0 and math.isfinite(ridge)):
            raise ValueError(f"ridge must be >= 0, got {ridge}")
        if flat_field and window < period:
            raise ValueError(f"the flat-field constraint needs a window of at least one CFA period ({period} px), "
                             f"got {window} px")
        self.period, self.bands, self.window, self.ridge = int(period), int(bands), int(window), float(ridge)
        self.flat_field = bool(flat_field)
        n = window * window
        self.gram = torch.zeros(period * period, n, n, dtype=torch.float64)
        self.cross = torch.zeros(period * period, n, bands, dtype=torch.float64)

    def add(self, sensor: torch.Tensor, truth: torch.Tensor, origin: tuple[int, int] = (0, 0)) -> None:
        if sensor.dim() != 4 or sensor.shape[1] != 1 or truth.shape != (sensor.shape[0], self.bands, *sensor.shape[-2:]):
            raise ValueError(f"need sensor (B, 1, H, W) and truth (B, {self.bands}, H, W) on the same pixels, got "
                             f"{tuple(sensor.shape)} and {tuple(truth.shape)}")
        r, m = self.window // 2, self.period
        h, w = sensor.shape[-2:]
        sensor, truth = sensor.detach().cpu().double(), truth.detach().cpu().double()
        padded = F.pad(sensor, (r, r, r, r), mode="replicate") if r else sensor
        k = self.window
        patches = padded[:, 0].unfold(1, k, 1).unfold(2, k, 1).reshape(-1, k * k)  # (B·H·W, K²)
        values = truth.permute(0, 2, 3, 1).reshape(-1, self.bands)
        rows = (torch.arange(h) + origin[0]) % m
        cols = (torch.arange(w) + origin[1]) % m
        phase = (rows[:, None] * m + cols[None, :]).reshape(-1).repeat(sensor.shape[0])
        for p in range(m * m):
            sel = phase == p
            x = patches[sel]
            self.gram[p] += x.T @ x
            self.cross[p] += x.T @ values[sel]

    def solve(self) -> torch.Tensor:
        n = self.gram.shape[-1]
        eye = torch.eye(n, dtype=torch.float64)
        grams = []
        for gram in self.gram:
            reg = self.ridge * torch.trace(gram) / n
            if not reg > 0:
                reg = 1e-12 if torch.trace(gram) > 0 else 1.0
            grams.append(gram + reg * eye)
        if self.flat_field:
            out = self._solve_flat_field(grams)
        else:
            out = [torch.linalg.solve(g, c) for g, c in zip(grams, self.cross)]  # (K², C) each
        k = self.window
        return torch.stack(out).transpose(1, 2).reshape(len(out), self.bands, k, k).float()

    def tap_phases(self) -> torch.Tensor:
        """S (m², m², K²): S[q, p, tap] = 1 where, for an output pixel of phase q, the tap (row-major
        in the K×K window) reads a pixel of phase p."""
        m, k, r = self.period, self.window, self.window // 2
        u = torch.arange(k) - r
        select = torch.zeros(m * m, m * m, k * k, dtype=torch.float64)
        for q in range(m * m):
            rows, cols = (q // m + u) % m, (q % m + u) % m
            p = (rows[:, None] * m + cols[None, :]).reshape(-1)
            select[q, p, torch.arange(k * k)] = 1.0
        return select

    def _solve_flat_field(self, grams: list[torch.Tensor]) -> list[torch.Tensor]:
        """Least squares under S_q w_q = M for all phases q (the Lagrange conditions, see above)."""
        select = self.tap_phases()
        g_inv_c, g_inv_st, h_inv = [], [], []
        for gram, cross, s in zip(grams, self.cross, select):
            both = torch.linalg.solve(gram, torch.cat([cross, s.T], 1))  # G⁻¹[c, Sᵀ]
            g_inv_c.append(both[:, : self.bands])
            g_inv_st.append(both[:, self.bands :])
            h_inv.append(torch.linalg.inv(s @ g_inv_st[-1]))  # H_q⁻¹ = (S G⁻¹ Sᵀ)⁻¹
        common = torch.linalg.solve(sum(h_inv), sum(h @ s @ gc for h, s, gc in zip(h_inv, select, g_inv_c)))  # M
        return [gc - gst @ (h @ (s @ gc - common)) for gc, gst, h, s in zip(g_inv_c, g_inv_st, h_inv, select)]
