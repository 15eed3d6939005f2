"""Writes the assets of spheres_room: meshes/torus.obj (a UV-mapped torus) and textures/tiles.png (floor tiles).

Run from anywhere: ``python examples/scenes/spheres_room/make_assets.py``. Deterministic; the outputs are
committed, so the scene folder is self-contained like a downloaded one (scene.xml references them by
relative paths).
"""
from __future__ import annotations

import math
import struct
import zlib
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def torus_obj(major: float = 1.0, minor: float = 0.35, rings: int = 32, sides: int = 16) -> str:
    """OBJ text of a torus about the y axis (radius ``major`` to the tube centre, tube radius ``minor``):
    positions, UVs (u around the ring, v around the tube), normals and quads split into triangles."""
    lines = ["# torus for spheres_room (make_assets.py)"]
    for i in range(rings + 1):
        phi = 2 * math.pi * i / rings
        for j in range(sides + 1):
            theta = 2 * math.pi * j / sides
            normal = (math.cos(theta) * math.cos(phi), math.sin(theta), math.cos(theta) * math.sin(phi))
            centre = (major * math.cos(phi), 0.0, major * math.sin(phi))
            position = tuple(c + minor * n for c, n in zip(centre, normal))
            lines.append("v {:.6f} {:.6f} {:.6f}".format(*position))
            lines.append(f"vt {i / rings:.6f} {j / sides:.6f}")
            lines.append("vn {:.6f} {:.6f} {:.6f}".format(*normal))
    stride = sides + 1
    for i in range(rings):
        for j in range(sides):
            a, b = i * stride + j + 1, (i + 1) * stride + j + 1
            for tri in ((a, a + 1, b + 1), (a, b + 1, b)):
                lines.append("f " + " ".join(f"{k}/{k}/{k}" for k in tri))
    return "\n".join(lines) + "\n"


def tiles_rgb(size: int = 128, tiles: int = 8) -> np.ndarray:
    """(size, size, 3) uint8 sRGB floor tiles: alternating warm greys with dark grout lines."""
    cell = size // tiles
    y, x = np.mgrid[0:size, 0:size]
    parity = ((x // cell) + (y // cell)) % 2
    base = np.where(parity[..., None] == 0, [168, 160, 146], [92, 88, 82]).astype(np.float64)
    grout = ((x % cell) < 2) | ((y % cell) < 2)
    base[grout] = [40, 38, 36]
    return base.astype(np.uint8)


def png_bytes(rgb: np.ndarray) -> bytes:
    """A minimal 8-bit RGB PNG (no dependency beyond zlib)."""
    height, width, _ = rgb.shape
    raw = b"".join(b"\x00" + rgb[row].tobytes() for row in range(height))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b"")


def main() -> None:
    (HERE / "meshes").mkdir(exist_ok=True)
    (HERE / "textures").mkdir(exist_ok=True)
    (HERE / "meshes" / "torus.obj").write_text(torus_obj())
    (HERE / "textures" / "tiles.png").write_bytes(png_bytes(tiles_rgb()))


if __name__ == "__main__":
    main()
