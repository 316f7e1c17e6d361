"""Reconstruction of whole sensor images, tile by tile.

The networks are local (each declares its ``context_px``), so a tile computed with a halo of at
least that many pixels on every side equals the same region of a whole-image pass: tiles are cut
with that halo and only their centres are kept, which makes the mosaic seamless (exactly, not by
blending) while memory stays bounded by the tile size: besides the output, one window and its
reconstruction are held at a time (the network's own working set, about 12× the window's cube for
``pretrained:standard``, is the largest part). Reading captures: :mod:`hsicam.data.images`.
"""

from __future__ import annotations

import inspect
import math
import numbers
from dataclasses import dataclass
from typing import Callable

import torch

from hsicam.cameras.base import check_finite, check_sensor_image
from hsicam.errors import InputError
from hsicam.memory import release_freed_memory


#: The range (px) of :func:`default_tile_px`.
MIN_DEFAULT_TILE_PX, MAX_DEFAULT_TILE_PX = 512, 1024


def default_tile_px(halo_px: int) -> int:
    """The tile side (px) that :func:`reconstruct_tiled` (and so ``reconstruct`` and ``evaluate``) uses unless
    told: 4 halos, within [512, 1024], so that each tile's window holds at most (1 + 2·¼)² = 2.25× its own
    pixels up to a 256 px halo (512 px tiles with the quick demo camera's 230 px halo: 3.6×; its 884² image
    took 66 s in 512 px tiles, 26 s whole, 1.4 GB, session 35). The tile, not its window (tile + 2 halos), is
    capped: memory grows with the halo beyond 256 px."""
    return min(max(MIN_DEFAULT_TILE_PX, 4 * int(halo_px)), MAX_DEFAULT_TILE_PX)


#: Peak memory of a reconstruction (:func:`reconstruction_memory_bytes`): the process and the model (0.40–0.45 GB
#: resident for ``pretrained:standard`` before it starts, 0.27 GB for the tiny preset; session 60), plus
#: :func:`reconstruction_working_bytes`, fitted to the peak resident memory that reconstructions added in fresh
#: processes (session 60, ``hsicam.memory.keep_freed_memory`` applied as the command does; the standard camera and the
#: tiny preset with and without 12 Landweber/TV steps, 128²–1536², whole and in 128–300 px tiles): 1.05–1.4× of it
#: (the same run's peak varies by up to 15 %).
RECONSTRUCT_BASE_BYTES = 512 * 2**20
RECONSTRUCT_FIXED_BYTES = 8 * 2**20  # what any reconstruction adds besides its cubes (threads, small tensors)
#: The network's (and linear step's) working set, in (C, window) float32 cubes: 8–13.4 measured (more with several
#: windows, whose freed memory the kept heap does not always reuse), the output cube besides.
WINDOW_CUBES = 13
#: The consistency steps' working set, in float32 values per pixel (C bands + 1-band planes): (cubes, planes) over
#: the whole frame (the image and the steps' margin: estimate, previous estimate, TV dual fields, brightness, row
#: sums, the network's output, what the kept heap holds from the network) and over one band of rows with its halo
#: (a step's temporaries; the whole frame when it is one band: :data:`~hsicam.models.consistency.STEP_BAND_PIXELS`).
STEP_FRAME_VALUES = {"landweber": (5, 16), "tv": (8, 0)}
STEP_BAND_VALUES = {"landweber": (5, 16), "tv": (18, 30)}


def reconstruction_working_bytes(reconstruct, bands: int, h: int, w: int, tile_px: int | None = None) -> int:
    """About the peak memory (bytes) that :func:`reconstruct_tiled` of an (h, w) image into ``bands`` bands adds to
    the process that holds ``reconstruct`` (a :meth:`CameraSystem.reconstructor`): the output cube, and the larger of
    one tile's window through the network (:data:`WINDOW_CUBES`) and the consistency steps' whole-image state and
    one band's temporaries (:data:`STEP_FRAME_VALUES`, :data:`STEP_BAND_VALUES`)."""
    from hsicam.models.consistency import TV_REACH_PX, WIENER_WINDOW_PX, _band_rows, default_band_px

    steps = getattr(reconstruct, "steps", None)
    before = getattr(reconstruct, "before_steps", reconstruct)
    halo = int(getattr(before, "context_px", 0) or 0)
    tile = default_tile_px(halo) if tile_px is None else int(tile_px)
    # the largest window reconstruct_tiled cuts: a tile and a halo each side, within the image; the whole image for a
    # reconstruction that cannot be tiled (SD-CASSI)
    window = min(tile + 2 * halo, h) * min(tile + 2 * halo, w) if _tileable(before) else h * w
    network = WINDOW_CUBES * bands * window
    work = 0
    if steps is not None and int(getattr(steps, "count", 1) or 0) > 0:
        kind = "tv" if getattr(steps, "tv", False) else "landweber"
        pad = int(getattr(steps, "frame_px", 0) or 0)
        fh, fw = h + 2 * pad, w + 2 * pad
        step_halo = 2 * pad + WIENER_WINDOW_PX // 2 + (TV_REACH_PX if kind == "tv" else 0)
        band = _band_rows(fh, default_band_px(w), step_halo)
        band_h = fh if band is None else min(band + 2 * step_halo, fh)
        (fc, fp), (bc, bp) = STEP_FRAME_VALUES[kind], STEP_BAND_VALUES[kind]
        work = (fc * bands + fp) * fh * fw + (bc * bands + bp) * band_h * fw
    return int(RECONSTRUCT_FIXED_BYTES + 4 * (bands * h * w + max(network, work)))


def reconstruction_memory_bytes(reconstruct, bands: int, h: int, w: int, tile_px: int | None = None) -> int:
    """About the peak memory (bytes) of :func:`reconstruct_tiled` of an (h, w) image into ``bands`` bands
    with ``reconstruct`` (a :meth:`CameraSystem.reconstructor`): the process and its model
    (:data:`RECONSTRUCT_BASE_BYTES`) and :func:`reconstruction_working_bytes`. An estimate for a refusal before the
    work, 1.05–1.4× the measured peaks of what the reconstruction adds (session 60)."""
    return RECONSTRUCT_BASE_BYTES + reconstruction_working_bytes(reconstruct, bands, h, w, tile_px)


@dataclass(frozen=True)
class MemoryShortfall:
    """What a refusal for memory says (:func:`memory_shortfall`): the work's ``need`` and the ``have`` the process may
    take (bytes), which limit that is (``limit``: :func:`hsicam.memory.process_memory_limit`'s words), and the side
    (px) of the largest square image whose work fits (``fits_px``; 0: none)."""

    need: int
    have: int
    limit: str
    fits_px: int


def memory_shortfall(need_of: Callable[[int, int], int], shape: tuple[int, int]) -> MemoryShortfall | None:
    """None when the work on an image of ``shape`` (H, W) fits the memory the process may take, else its
    :class:`MemoryShortfall`. ``need_of(h, w)``: the peak (bytes) of the work on an (h, w) image, growing with it
    (:func:`reconstruction_memory_bytes` for ``reconstruct``, :func:`hsicam.engine.evaluate.evaluation_memory_bytes`
    for ``evaluate``): the one check both commands make before minutes of work."""
    from hsicam.memory import process_memory_limit

    have, limit = process_memory_limit()
    need = need_of(*shape)
    if have is None or need <= have:
        return None
    lo, hi = 0, max(shape)  # the largest square part that fits: lo fits (0: none), hi does not
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if need_of(mid, mid) <= have else (lo, mid)
    return MemoryShortfall(int(need), int(have), limit, lo)


def tiled_pixels(shape: tuple[int, int], tile_px: int, halo_px: int) -> int:
    """The pixels that :func:`reconstruct_tiled`'s windows of an image of ``shape`` (H, W) add up to, in tiles of
    ``tile_px`` with ``halo_px`` around each (cut to the image; one window when the image fits a tile)."""
    if max(shape) <= tile_px:
        return math.prod(shape)

    def along(n: int) -> int:  # the windows' extents along one axis
        return sum(min(t + tile_px + halo_px, n) - max(t - halo_px, 0) for t in range(0, n, tile_px))

    return along(shape[0]) * along(shape[1])


def _declared(reconstruct, name: str):
    """The attribute ``name`` that ``reconstruct`` (or the object of a bound method, e.g. a :class:`CameraSystem`)
    declares, else None: ``context_px``, ``tileable``."""
    values = (getattr(x, name, None) for x in (reconstruct, getattr(reconstruct, "__self__", None)))
    return next((v for v in values if v is not None), None)


def _tileable(reconstruct) -> bool:
    """Whether ``reconstruct`` declares that its windows' cubes are their size: ``tileable``
    (:attr:`hsicam.models.CameraSystem.tileable`); one that declares nothing is taken as one."""
    declared = _declared(reconstruct, "tileable")
    return True if declared is None else bool(declared)


@torch.no_grad()
def reconstruct_tiled(reconstruct, sensor: torch.Tensor, tile_px: int | None = None, halo_px: int | None = None,
                      progress: bool | None = False) -> torch.Tensor:
    """Apply ``reconstruct`` ((1, 1, h, w) → (1, C, h, w)) to a (1, 1, H, W) image in tiles.

    If ``reconstruct`` takes an ``origin`` argument (e.g. :meth:`CameraSystem.reconstruct`), it
    is given each window's top-left sensor pixel, so position-dependent inputs (the CFA phase)
    line up with the whole image.

    Args:
        sensor: (1, 1, H, W) floating, finite (values in [0, 1]).
        tile_px: side of the kept centre of each tile (an int >= 1; default :func:`default_tile_px` of the halo).
        halo_px: context added around each tile (an int >= 0; ≥ the receptive radius for an exact
            result). Default: the ``context_px`` that ``reconstruct`` (or the object of a bound method,
            e.g. a :class:`CameraSystem`) declares, as :meth:`CameraSystem.reconstructor`'s does; an
            image larger than one tile needs it given otherwise (a halo of 0 leaves seams).
        progress: count the tiles (:class:`hsicam.progress.Progress`): None: a bar on a terminal, k/N
            log lines otherwise; True: the bar; False (default): nothing.

    A ``reconstruct`` with measurement-consistency steps after it (``reconstruct.before_steps`` and
    ``reconstruct.steps``, as :meth:`CameraSystem.reconstructor` gives; ``halo_px`` not given) is tiled up to
    its steps, with ``before_steps.context_px`` of halo (and tiles of :func:`default_tile_px` of that), and its
    steps then go over the whole image (in bands of rows, the same cube as tiles with their halo: each step
    reaches a few dozen px further: the shipped standard camera's 12 steps with a TV prior would need 463 px of
    halo where its network and linear step need 180; the camera shipped before session 68, 490 and 182 px, whose
    2048² capture in tiles with the steps' halo took 9.6 GB).

    A ``reconstruct`` that declares ``tileable`` False (a camera whose cube is not its sensor image's size: SD-CASSI)
    takes the whole image in one window; a ``tile_px`` smaller than the image is then one :class:`InputError`, before
    anything is computed.
    """
    for name, value, low in (("tile_px", 1 if tile_px is None else tile_px, 1),
                             ("halo_px", 0 if halo_px is None else halo_px, 0)):
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low:
            raise InputError(f"{name} must be an int >= {low}, got {value!r}")
    if isinstance(sensor, torch.Tensor) and (sensor.dim() != 4 or sensor.shape[:2] != (1, 1)):
        raise InputError(f"sensor image must be (1, 1, H, W), got {tuple(sensor.shape)}")
    check_sensor_image(sensor, "sensor")
    check_finite(sensor, "sensor")
    _, _, h, w = sensor.shape
    steps = getattr(reconstruct, "steps", None)
    if halo_px is None and steps is not None:  # tiles up to the steps, which then go over the whole image
        before = reconstruct.before_steps
        tile_px = default_tile_px(before.context_px) if tile_px is None else tile_px
        # (an image of one tile too: the same cube as reconstruct(sensor), and the steps' progress is shown)
        x = reconstruct_tiled(before, sensor, tile_px, None, progress)
        from hsicam.progress import Progress

        with Progress(int(getattr(steps, "count", 0)) or 1, "consistency steps", "step", show=progress) as bar:
            return steps(sensor, x, on_step=lambda: bar.update(1))
    if not _tileable(reconstruct):  # (SD-CASSI: its cube is not the sensor image's size) one window, the whole image
        if tile_px is not None and (h > tile_px or w > tile_px):
            raise InputError(f"a tile of {tile_px} px: this reconstruction cannot be tiled (its camera's scene grid is "
                             f"not the sensor's, e.g. SD-CASSI), so the {h}×{w} px image is reconstructed whole: drop the "
                             f"tile size or give one of at least {max(h, w)} px")
        return reconstruct(sensor)
    if halo_px is None:
        declared = _declared(reconstruct, "context_px")
        halo_px = None if declared is None else int(declared)
    if tile_px is None:
        tile_px = default_tile_px(halo_px or 0)
    if halo_px is None and (h > tile_px or w > tile_px):
        raise InputError(f"halo_px is needed: {type(reconstruct).__name__} declares no context_px, and the "
                         f"{h}×{w} px image is cut into {tile_px} px tiles (pass the reconstruction's context "
                         "per side, e.g. a CameraSystem's context_px attribute; a halo of 0 leaves seams)")
    takes_origin = "origin" in inspect.signature(reconstruct).parameters
    if h <= tile_px and w <= tile_px:
        return reconstruct(sensor)
    out = None
    ny, nx = math.ceil(h / tile_px), math.ceil(w / tile_px)
    from hsicam.progress import Progress

    with Progress(ny * nx, "reconstruct", "tile", show=progress) as bar:
        for ty in range(ny):
            for tx in range(nx):
                y0, x0 = ty * tile_px, tx * tile_px
                y1, x1 = min(y0 + tile_px, h), min(x0 + tile_px, w)
                ya, xa = max(y0 - halo_px, 0), max(x0 - halo_px, 0)
                yb, xb = min(y1 + halo_px, h), min(x1 + halo_px, w)
                window = sensor[..., ya:yb, xa:xb]
                part = reconstruct(window, origin=(ya, xa)) if takes_origin else reconstruct(window)
                if part.shape[-2:] != window.shape[-2:]:
                    raise InputError(f"the reconstruction of a {tuple(window.shape[-2:])} px window is "
                                     f"{tuple(part.shape[-2:])} px (a camera whose scene grid is not the sensor's, "
                                     f"e.g. SD-CASSI): it cannot be tiled; use a tile of at least {max(h, w)} px")
                if out is None:
                    out = torch.empty(1, part.shape[1], h, w, dtype=part.dtype, device=part.device)
                out[..., y0:y1, x0:x1] = part[..., y0 - ya : y1 - ya, x0 - xa : x1 - xa]
                del part  # freed before the next window is computed: one window's cube at a time, not two
                release_freed_memory()  # the hsicam command's kept heap: not one tile's fragments into the next
                bar.update(1)
    return out
