"""Lines of the data readers and previews that the default suite never ran (coverage round 10, cov10a)."""

from __future__ import annotations

import json
import logging
import struct

import numpy as np
import pytest
import tifffile

from hsicam.data.images import RawCorrection, read_image_2d
from hsicam.errors import InputError
from hsicam.spectral import Bands


# ------------------------------------------------------------------------------------------------
# TIFF pages that tifffile decodes only with imagecodecs (LZW) or not at all (JPEG): Pillow's path
# ------------------------------------------------------------------------------------------------
def _lzw_literal(data: bytes) -> bytes:
    """TIFF LZW of ``data`` with literal codes only (a Clear code every 250 bytes keeps them 9 bits wide)."""
    codes = []
    for i in range(0, len(data), 250):
        codes += [256] + list(data[i:i + 250])
    codes.append(257)  # end of information
    bits = "".join(format(c, "09b") for c in codes)
    bits += "0" * (-len(bits) % 8)
    return int(bits, 2).to_bytes(len(bits) // 8, "big")


def _lzw_tiff(path, image: np.ndarray, order: str) -> None:
    """A single-strip grey TIFF of ``image``, LZW-compressed, in byte order ``order`` ("<" II, ">" MM), written
    field by field after the TIFF 6.0 specification (tifffile writes LZW only with imagecodecs)."""
    h, w = image.shape
    dt = image.dtype
    strip = _lzw_literal(image.astype(dt.newbyteorder(order)).tobytes())
    fmt = {"u": 1, "i": 2, "f": 3}[dt.kind]
    tags = [(256, 3, w), (257, 3, h), (258, 3, 8 * dt.itemsize), (259, 3, 5), (262, 3, 1), (273, 4, 0),
            (277, 3, 1), (278, 3, h), (279, 4, len(strip)), (339, 3, fmt)]
    offset = 8 + 2 + 12 * len(tags) + 4
    out = (b"MM\x00*" if order == ">" else b"II*\x00") + struct.pack(order + "IH", 8, len(tags))
    for tag, typ, value in tags:
        value = offset if tag == 273 else value
        field = struct.pack(order + "H", value) + b"\0\0" if typ == 3 else struct.pack(order + "I", value)
        out += struct.pack(order + "HHI", tag, typ, 1) + field
    path.write_bytes(out + struct.pack(order + "I", 0) + strip)


@pytest.mark.parametrize("order", ["<", ">"])
def test_a_big_endian_lzw_tiff_reads_as_the_little_endian_one(tmp_path, order):
    """A 16-bit LZW TIFF in Motorola byte order ("MM", big-endian) was refused: "TIFF compressed with LZW, which
    neither tifffile without the imagecodecs package nor Pillow decodes here ... (Pillow decodes it as >u2 (20, 30),
    not uint16 (20, 30))" although Pillow had decoded it right; only its byte order differed from tifffile's."""
    image = (np.random.default_rng(5).random((20, 30)) * 4000).astype(np.uint16)
    _lzw_tiff(tmp_path / "lzw.tif", image, order)
    with tifffile.TiffFile(tmp_path / "lzw.tif") as tf:
        assert tf.byteorder == order and tf.pages[0].compression == 5
    got = read_image_2d(tmp_path / "lzw.tif", "sensor image")
    np.testing.assert_array_equal(got.data, image.astype(np.float32))
    assert got.full_scale == 65535.0 and got.dtype == "uint16" and got.format == "tiff"
