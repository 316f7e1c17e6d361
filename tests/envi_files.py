"""ENVI test files written as ENVI software writes them: a text header and the raw stored values."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def write_envi_pair(folder: Path, chw: np.ndarray, extra: str, waves, dtype: str = "<u2", code: int = 12,
                    interleave: str = "bil") -> Path:
    """``folder/scene.hdr`` + ``scene.img`` holding ``chw`` (C, H, W) as ``dtype`` (ENVI data type
    ``code``) in ``interleave`` order, little-endian, bands at ``waves[:C]`` nm; ``extra``: more
    header lines. Returns the header's path."""
    c, h, w = chw.shape
    hdr = folder / "scene.hdr"
    hdr.write_text(f"ENVI\nsamples = {w}\nlines = {h}\nbands = {c}\nheader offset = 0\nfile type = ENVI Standard\n"
                   f"data type = {code}\ninterleave = {interleave}\nbyte order = 0\nwavelength units = Nanometers\n"
                   f"wavelength = {{{', '.join(f'{v:g}' for v in waves[:c])}}}\n{extra}")
    disk = {"bsq": chw, "bil": chw.transpose(1, 0, 2), "bip": chw.transpose(1, 2, 0)}[interleave]
    (folder / "scene.img").write_bytes(np.ascontiguousarray(disk).astype(dtype).tobytes())
    return hdr
