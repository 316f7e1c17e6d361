"""The paper's camera: lens + learned DOE + learned periodic CFA on a monochrome sensor.

    g = Σ_λ (f_λ ⊛ p_λ) ⊙ κ_λ + e        (paper eq. 2)

``A`` is the noiseless linear map; ``A_adjoint`` its exact adjoint; ``forward`` draws DOE height
noise (when σ_p > 0) and sensor noise.
"""

from __future__ import annotations

import torch

from hsicam.cameras.base import Camera, check_origin, check_window_size
from hsicam.cameras.registry import register_camera
from hsicam.errors import InputError
from hsicam.optics.convolution import (
    coded_conv_same,
    coded_conv_same_adjoint,
    coded_conv_valid,
    coded_conv_valid_adjoint,
    linear_fft_shape,
    pad_same,
    pad_same_adjoint,
    same_spectra,
)
from hsicam.optics.doe import DOE
from hsicam.optics.lens import lens_from_config
from hsicam.optics.psf import PSFModel, PSFResult
from hsicam.optics.pupil import cells_across
from hsicam.sensor import ColorFilterArray, SensorNoise, tile_pattern
from hsicam.spectral import Bands, get_material


#: Bytes per DOE cell while the element is made and trained: the float64 draw of its heights, the
#: float32 parameter, its gradient and Adam's two moments (a DOE switched off keeps a float32 grid of
#: zeros: 4); the PSF's pupil needs more again (:func:`hsicam.optics.sampling.check_psf_memory`, next).
DOE_BYTES_PER_CELL = 8 + 4 * 4


def check_doe_memory(n_cells: int, cell_size_um: float, aperture_radius_mm: float, enabled: bool = True) -> None:
    """ConfigError, before the height map is allocated, for a DOE of more cells than the memory
    budget holds (a cell size in the wrong unit: 0.05 µm across a 1.2 mm aperture is 24 000 cells a
    side, 4.6 GB for the first draw alone), naming the two keys that set the count."""
    from hsicam.errors import ConfigError
    from hsicam.memory import MEMORY_BUDGET_ENV, format_bytes, memory_budget_bytes

    need, budget = (DOE_BYTES_PER_CELL if enabled else 4) * n_cells**2, memory_budget_bytes()
    if need > budget:
        raise ConfigError(f"camera.doe.cell_size_um={cell_size_um:g} across the {2 * aperture_radius_mm:g} mm aperture "
                          f"(2 × camera.aperture_radius_mm) is a DOE of {n_cells:,}×{n_cells:,} cells, whose heights "
                          f"alone need {format_bytes(need)}, more than the memory budget of {format_bytes(budget)} "
                          f"({MEMORY_BUDGET_ENV}); check the cell size (in µm) or the aperture (in mm)")


#: Bytes per CFA weight while the filters are made and trained: the float32 parameter, its gradient and
#: Adam's two moments (the band-pass init's float64 draft aside, transient).
CFA_BYTES_PER_WEIGHT = 4 * 4


def check_cfa_memory(period: int, n_bands: int, enabled: bool = True) -> None:
    """ConfigError, before the filter weights are allocated, for a CFA of more weights (bands × period²)
    than the memory budget holds (``camera.cfa.period=100000`` asked torch for 280 GB and failed in a
    traceback; a period beyond int64 failed in torch's argument parsing), naming the key."""
    from hsicam.errors import ConfigError
    from hsicam.memory import MEMORY_BUDGET_ENV, format_bytes, memory_budget_bytes

    if not enabled:
        return
    need, budget = CFA_BYTES_PER_WEIGHT * n_bands * period**2, memory_budget_bytes()
    if need > budget:
        raise ConfigError(f"camera.cfa.period={period} is a CFA tile of {period:,}×{period:,} px whose {n_bands} "
                          f"filter weights per pixel need {format_bytes(need)}, more than the memory budget of "
                          f"{format_bytes(budget)} ({MEMORY_BUDGET_ENV}); a CFA period is a few pixels (the paper's: 3 to 15)")


@register_camera("doe")
class DOECamera(Camera):
    """Differentiable DOE camera. Build it with :meth:`from_config`.

    Args:
        bands: band grid (C bands).
        optics: lens + DOE PSF model.
        cfa: colour filter array.
        noise: sensor noise.
        boundary: "valid" or "same".
        padding: scene padding for "same" ("zeros", "reflect", "replicate", "circular").
    """

    half_precision_on_cpu = False  # torch's CPU FFTs have no float16/bfloat16

    def __init__(self, bands: Bands, optics: PSFModel, cfa: ColorFilterArray, noise: SensorNoise,
                 boundary: str = "valid", padding: str = "zeros") -> None:
        super().__init__()
        if boundary not in ("valid", "same"):
            raise ValueError(f"boundary must be 'valid' or 'same', got {boundary!r}")
        if cfa.n_bands != len(bands):
            raise ValueError(f"CFA has {cfa.n_bands} bands, the camera {len(bands)}")
        self.bands, self.optics, self.cfa, self.noise = bands, optics, cfa, noise
        self.boundary, self.padding = boundary, padding

    @classmethod
    def from_config(cls, cfg) -> "DOECamera":  # cfg: hsicam.config.Config
        """Camera from a top-level :class:`~hsicam.config.Config` (uses ``cfg.bands`` and ``cfg.camera``)."""
        bands = cfg.bands.to_bands()
        cam = cfg.camera
        cell_m = cam.doe.cell_size_um * 1e-6
        n_cells = cells_across(cam.aperture_radius_mm * 1e-3, cell_m)
        check_doe_memory(n_cells, cam.doe.cell_size_um, cam.aperture_radius_mm, cam.doe.enabled)
        doe = DOE(
            n_cells, get_material(cam.doe.material, "camera.doe.material"), cam.doe.design_wavelength_nm,
            cam.doe.enabled,
            cam.doe.init, cam.doe.seed,
            None if cam.doe.max_height_nm is None else cam.doe.max_height_nm * 1e-9,
            cam.doe.wrap, cam.doe.quantization_levels, cam.doe.sigma_height_nm * 1e-9,
            None if cam.doe.init_range_nm is None else cam.doe.init_range_nm * 1e-9,
            cam.doe.init_correlation_cells, cam.doe.init_grating_period_cells,
        )
        optics = PSFModel(
            bands, lens_from_config(cam.lens), doe, cam.aperture_radius_mm * 1e-3, cell_m,
            cam.sensor.pixel_pitch_um * 1e-6, cam.lens.design_wavelength_nm,
            None if cam.sensor_distance_mm is None else cam.sensor_distance_mm * 1e-3,
            cam.object_distance_m, cam.psf.kernel_px, cam.psf.supersample, cam.psf.pupil_oversample,
            cam.psf.band_samples,
        )
        check_cfa_memory(cam.cfa.period, len(bands), cam.cfa.enabled)
        cfa = ColorFilterArray(len(bands), cam.cfa.period, cam.cfa.enabled, cam.cfa.seed, cam.cfa.init,
                               bands.centers_nm, cam.cfa.bandpass_fwhm_nm, cam.cfa.layout)
        s = cam.sensor
        noise = SensorNoise.from_config(s)
        return cls(bands, optics, cfa, noise, cam.boundary, cam.padding)

    def noise_levels(self) -> dict[str, float]:
        """``sensor_sigma`` and ``sigma_height_nm`` (DOE fabrication noise per cell, nm)."""
        return {**super().noise_levels(), "sigma_height_nm": float(self.optics.doe.sigma_height_m) * 1e9}

    def _apply_noise(self, levels: dict[str, float]) -> None:
        super()._apply_noise(levels)
        if "sigma_height_nm" in levels:
            self.optics.doe.sigma_height_m = float(levels["sigma_height_nm"]) * 1e-9

    def param_groups(self) -> dict[str, list[torch.nn.Parameter]]:
        """``doe`` (height map, m) and ``cfa`` (filter weights) when enabled."""
        groups: dict[str, list[torch.nn.Parameter]] = {}
        if self.optics.doe.enabled:
            groups["doe"] = [self.optics.doe.height_m]
        if self.cfa.enabled:
            groups["cfa"] = [self.cfa.weights]
        return groups

    def param_group_spans(self) -> dict[str, tuple[float, str]]:
        """``doe``: the span of the heights (m), the top of :meth:`~hsicam.optics.doe.DOE.level_grid`: the
        clamp range ``max_height`` when heights are clamped without wrapping, else h_2π at the design
        wavelength (a whole phase period); ``cfa``: 1, the range of the weights, which start in [0, 1]
        and pass a ReLU and a per-pixel normalisation (:func:`hsicam.sensor.cfa_tile`)."""
        doe = self.optics.doe
        top, wraps = doe.level_grid()
        what = (f"the DOE's whole phase period, h_2π = {top * 1e9:.4g} nm at its design wavelength "
                f"{doe.design_wavelength_nm:g} nm" if wraps else
                f"the DOE heights' whole clamp range camera.doe.max_height_nm = {top * 1e9:.4g} nm")
        return {"doe": (top, what), "cfa": (1.0, "the CFA weights' whole range [0, 1]")}

    @property
    def kernel_px(self) -> int:
        return self.optics.kernel_px

    @property
    def margin(self) -> int:
        return self.kernel_px - 1

    def psf_result(self, generator: torch.Generator | None = None) -> PSFResult:
        """PSF stack (C, K, K) and per-band energy inside the kernel."""
        return self.optics(generator)

    def psf(self, generator: torch.Generator | None = None) -> torch.Tensor:
        """PSF stack (C, K, K); draws DOE height noise when σ_p > 0."""
        return self.optics(generator).psf

    def A(self, x: torch.Tensor, psf: torch.Tensor | None = None) -> torch.Tensor:  # noqa: N802
        """Noiseless sensor image (B, 1, H, W) of the scene ``x`` (B, C, H', W').

        ``psf`` (C, K, K) may be passed to reuse one PSF computation (e.g. in iterative solvers).
        """
        self.check_scene(x)
        psf = self.psf() if psf is None else psf
        if self.boundary == "same":
            x = pad_same(x, self.kernel_px, self.padding)
        h, w = x.shape[-2] - self.margin, x.shape[-1] - self.margin
        kappa = self.cfa.pattern(h, w).to(x.dtype)
        return coded_conv_valid(x, psf.to(x.dtype), kappa)

    def A_adjoint(self, g: torch.Tensor, psf: torch.Tensor | None = None) -> torch.Tensor:  # noqa: N802
        """Exact adjoint of :meth:`A`: sensor image (B, 1, H, W) → cube (B, C, H', W')."""
        self.check_measurement(g)
        self.check_padded_size(tuple(g.shape[-2:]), "sensor image")  # a `same` image is the scene's size
        psf = self.psf() if psf is None else psf
        kappa = self.cfa.pattern(g.shape[-2], g.shape[-1]).to(g.dtype)
        x = coded_conv_valid_adjoint(g, psf.to(g.dtype), kappa)
        if self.boundary == "same":
            x = pad_same_adjoint(x, self.kernel_px, self.padding)
        return x

    @property
    def code_period(self) -> int:
        """Period of the sensor code in pixels (the CFA's m; 1 without a CFA)."""
        return self.cfa.period if self.cfa.enabled else 1

    def sensor_code(self, height: int, width: int, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
        """The CFA transmission κ (C, height, width) of the sensor window at ``origin``."""
        check_window_size(height, width)
        check_origin(origin)
        return self.cfa.pattern(height, width, origin)

    def forward(self, x: torch.Tensor, generator: torch.Generator | None = None, *,
                sensor_generator: torch.Generator | None = None) -> torch.Tensor:
        """Noisy sensor image: DOE height noise (σ_p) drawn from ``generator``, sensor noise from
        ``sensor_generator`` if given (e.g. one fabricated element imaging several scenes, each capture
        with its own noise), else from ``generator`` too."""
        return self.noise(self.A(x, self.psf(generator)), generator if sensor_generator is None else sensor_generator)

    def measure(self, x: torch.Tensor, generator: torch.Generator | None = None):
        """(noisy sensor image, operator for the network). Without height noise the snapshot that
        made the image is the nominal operator, so it is passed on (one PSF computation per step);
        with height noise the network gets the camera (it uses the nominal PSF, not the draw)."""
        if self.optics.doe.sigma_height_m > 0:
            return self(x, generator), self
        snap = self.snapshot(generator)
        return self.noise(self.A(x, snap.psf), generator), snap

    def fixed_measure(self):
        """See :meth:`Camera.fixed_measure`: the nominal PSF stack is computed once, on the first
        call, and reused (a step's PSF costs 0.11 s of a quick network-only step's 0.37 s); while
        DOE height noise is on (σ_p > 0, e.g. drawn per step) every call draws its own PSF."""
        cached: list[DOESnapshot] = []

        def fn(x: torch.Tensor, generator: torch.Generator | None = None):
            with torch.no_grad():
                if self.optics.doe.sigma_height_m > 0:
                    return self.measure(x, generator)
                if not cached:
                    cached.append(self.snapshot())
                snap = cached[0]
                return self.noise(self.A(x, snap.psf), generator), snap

        return fn

    def snapshot(self, generator: torch.Generator | None = None, *, nominal: bool = False) -> "DOESnapshot":
        """The operator with one PSF draw (height noise from ``generator``; none if ``nominal``)
        and the current CFA, in ``same`` geometry with zero padding: see :class:`DOESnapshot`."""
        if nominal and self.optics.doe.sigma_height_m > 0:
            saved, self.optics.doe.sigma_height_m = self.optics.doe.sigma_height_m, 0.0
            try:
                psf = self.psf(generator)
            finally:
                self.optics.doe.sigma_height_m = saved
        else:
            psf = self.psf(generator)
        return DOESnapshot(self.bands, psf, self.cfa.tile(), self.code_period)


class DOESnapshot:
    """The DOE camera's operator frozen for one batch, on sensor-sized cubes (``same``, zero padding):

        A(x)_{origin} = Σ_c κ_c ⊙ (p_c ⊛ pad₀(x_c))     x (B, C, h, w) → (B, 1, h, w)
        Aᵀ(y)         = crop(p_c ⋆ (κ_c ⊙ y))            (B, 1, h, w) → (B, C, h, w)

    κ is the CFA over the sensor window whose top-left pixel is ``origin`` (the CFA phase). The
    PSF stack (C, K, K) and the CFA tile (C, m, m) are the tensors captured from the camera, so
    gradients reach the DOE heights and the CFA weights. Light from outside the window is taken as
    zero: on a crop of a larger scene (a ``valid`` training patch), A x differs from the
    measurement within K//2 px of the border.

    Applied without gradients (inference: the consistency steps call A and Aᵀ a few dozen times on windows of
    one size), the snapshot keeps the PSFs' spectra and the CFA transmission of the last
    :data:`KEPT_WINDOWS` window sizes and phases it saw: 31 of a call's 62 FFTs and the CFA's (C, h, w) tiling
    are not redone (with the coded convolution's band-by-band CFA sum, A and Aᵀ of a 532² × 31 window went 117 →
    72 ms together; session 48). Nothing is kept while the PSFs or the CFA need gradients. Without gradients A and
    Aᵀ also skip the zero-padded copy of the cube and the (h + K − 1)² adjoint's crop (:func:`coded_conv_same`,
    :func:`coded_conv_same_adjoint`: 85–103 → 71–77 ms together, measured in the same hour; session 49).
    """

    #: How many window geometries (FFT shape; CFA size and phase) the kept spectra and CFA tilings cover: the
    #: steps of one image use one (a 2048² capture's bands of rows, about three: the first, the middle ones, the
    #: last), tiles of one size one more.
    KEPT_WINDOWS = 3

    def __init__(self, bands: Bands, psf: torch.Tensor, tile: torch.Tensor, code_period: int) -> None:
        self.bands, self.psf, self.tile, self.code_period = bands, psf, tile, int(code_period)
        k = psf.shape[-1]
        self.reach_px = (k - 1, k - 1)
        # ‖A‖² ≤ max_c ‖p_c‖₁² · max_pixel Σ_c κ_c² (Young + Cauchy–Schwarz)
        bound = psf.sum(dim=(-2, -1)).amax() ** 2 * tile.square().sum(0).amax()
        self.lipschitz = float(bound.detach())
        #: the same bound as a 0-dim tensor in the optics' autograd graph (None when they need no gradient): the
        #: unrolled network's steps α = softplus(θ)/L must see how L moves with the PSFs and the CFA, or the optics
        #: are trained by the gradient of another function (session 53: 48 % off for the CFA, the sign wrong in a probe)
        self.lipschitz_in_graph = bound if bound.requires_grad else None
        self._kept: dict = {}  # (what, geometry, dtype) → tensor, the oldest first

    def _keep(self, key: tuple, make, source: torch.Tensor) -> torch.Tensor:
        """``make()``, kept under ``key`` while ``source`` (the PSFs or the CFA tile) needs no gradient."""
        if torch.is_grad_enabled() and source.requires_grad:
            return make()
        if key in self._kept:
            return self._kept[key]
        same_kind = [k for k in self._kept if k[0] == key[0]]
        if len(same_kind) >= self.KEPT_WINDOWS:
            del self._kept[same_kind[0]]
        with torch.no_grad():
            self._kept[key] = make()
        return self._kept[key]

    def _spectra(self, scene_hw: tuple[int, int], dtype: torch.dtype) -> torch.Tensor | None:
        """The PSFs' spectra for a (padded) scene of ``scene_hw`` as the same-geometry convolutions take them
        (:func:`~hsicam.optics.convolution.same_spectra`), or None while the PSFs need gradients."""
        if torch.is_grad_enabled() and self.psf.requires_grad:
            return None
        shape = linear_fft_shape(scene_hw)
        return self._keep(("spectra", shape, dtype), lambda: same_spectra(self.psf.to(dtype), shape), self.psf)

    def _code(self, height: int, width: int, origin: tuple[int, int], dtype: torch.dtype) -> torch.Tensor:
        m = self.tile.shape[-2:]
        phase = (origin[0] % m[0], origin[1] % m[1])
        return self._keep(("code", (height, width, phase), dtype),
                          lambda: self.sensor_code(height, width, phase).to(dtype), self.tile)

    @property
    def kernel_px(self) -> int:
        return self.psf.shape[-1]

    def scene_size(self, sensor_hw: tuple[int, int]) -> tuple[int, int]:
        return tuple(sensor_hw)

    def sensor_code(self, height: int, width: int, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:
        """κ (C, height, width) of the sensor window at ``origin``."""
        check_window_size(height, width)
        check_origin(origin)
        tile = self.tile
        shift = (-(origin[0] % tile.shape[-2]), -(origin[1] % tile.shape[-1]))
        if shift != (0, 0):
            tile = torch.roll(tile, shifts=shift, dims=(-2, -1))
        return tile_pattern(tile, height, width)

    def _check_input(self, t: torch.Tensor, channels: int, what: str) -> None:
        """:class:`InputError` unless ``t`` is a floating (B, ``channels``, H, W) tensor that the FFT convolution
        takes: float32 or float64 on the CPU, on the PSFs' device (values are not scanned: the steps call A and Aᵀ
        dozens of times)."""
        if not isinstance(t, torch.Tensor):
            raise InputError(f"{what} must be a torch.Tensor (B, {channels}, H, W), got {type(t).__name__}")
        if t.dim() != 4 or t.shape[1] != channels:
            raise InputError(f"{what} must be (B, {channels}, H, W), got shape {tuple(t.shape)}")
        if not torch.is_floating_point(t):
            raise InputError(f"{what} is {t.dtype}: the DOE camera's FFT convolution takes floating-point tensors "
                             "(.float())")
        if t.device.type == "cpu" and t.dtype in (torch.float16, torch.bfloat16):
            raise InputError(f"{what} is {t.dtype} on the CPU: the DOE camera's FFT convolution takes float32 or "
                             "float64 there (.float())")
        if t.device != self.psf.device:
            raise InputError(f"{what} is on {t.device}, the camera's PSFs on {self.psf.device}: move one of them")

    def A(self, x: torch.Tensor, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:  # noqa: N802
        """Sensor window (B, 1, h, w) of the cube ``x`` (B, C, h, w)."""
        self._check_input(x, len(self.bands), "cube")
        kappa = self._code(x.shape[-2], x.shape[-1], origin, x.dtype)
        k = self.kernel_px
        spectra = self._spectra((x.shape[-2] + k - 1, x.shape[-1] + k - 1), x.dtype)
        return coded_conv_same(x, self.psf.to(x.dtype), kappa, spectra)

    def A_adjoint(self, y: torch.Tensor, origin: tuple[int, int] = (0, 0)) -> torch.Tensor:  # noqa: N802
        """Exact adjoint of :meth:`A`: (B, 1, h, w) → (B, C, h, w)."""
        self._check_input(y, 1, "sensor image")
        kappa = self._code(y.shape[-2], y.shape[-1], origin, y.dtype)
        k = self.kernel_px
        spectra = self._spectra((y.shape[-2] + k - 1, y.shape[-1] + k - 1), y.dtype)
        return coded_conv_same_adjoint(y, self.psf.to(y.dtype), kappa, spectra)

    def cropped(self, kernel_px: int) -> "DOESnapshot":
        """The same operator with each PSF cut to its central ``kernel_px`` (odd) pixels: cheaper,
        approximate (the light outside is dropped), still with an exact adjoint."""
        k = self.kernel_px
        if kernel_px % 2 == 0 or kernel_px < 1:
            raise ValueError(f"kernel_px must be odd and >= 1, got {kernel_px}")
        if kernel_px >= k:
            return self
        a = (k - kernel_px) // 2
        return DOESnapshot(self.bands, self.psf[:, a : a + kernel_px, a : a + kernel_px], self.tile, self.code_period)
