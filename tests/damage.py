"""Damaging a file as a disk error or an edit would, for tests of what readers refuse."""

from __future__ import annotations


def flip_byte_in_place(path, offset: int) -> None:
    """Flip the lowest bit of the byte at ``offset``, in place: the same size, the same inode."""
    with open(path, "r+b") as fh:
        fh.seek(offset)
        b = fh.read(1)
        fh.seek(offset)
        fh.write(bytes([b[0] ^ 0x01]))
