"""Textures of printed markers, and bilinear sampling (docs/design/ros_and_core.md)."""

from __future__ import annotations

from functools import cache

import cv2
import numpy as np

from slam_core.arrays import Float32Array

REMAP_WIDTH = 4096
"""cv2.remap takes fewer than 2 ** 15 rows and columns: larger lookups go in rows of this."""


@cache
def _predefined(name: str) -> cv2.aruco.Dictionary:
    value = getattr(cv2.aruco, name, None) if name.startswith('DICT_') else None
    if value is None:
        raise ValueError(f'unknown marker dictionary {name!r}: not a cv2.aruco DICT_* name')
    return cv2.aruco.getPredefinedDictionary(int(value))


def marker_texture(
    dictionary: str,
    marker_id: int,
    *,
    texels_per_cell: int,
    quiet_zone_texels: int,
    ink: float = 0.0,
    paper: float = 255.0,
) -> Float32Array:
    """Grey texture (N, N) float32 of a cv2.aruco marker printed on paper."""
    table = _predefined(dictionary)
    if not 0 <= marker_id < table.bytesList.shape[0]:
        raise ValueError(f'marker id {marker_id} is not in {dictionary}')
    if texels_per_cell < 1 or quiet_zone_texels < 0:
        raise ValueError(
            f'texels_per_cell {texels_per_cell} must be >= 1 and quiet_zone_texels '
            f'{quiet_zone_texels} >= 0'
        )
    cells = table.markerSize + 2
    tag = cv2.aruco.generateImageMarker(
        table, int(marker_id), cells * texels_per_cell, borderBits=1
    )
    quiet = quiet_zone_texels
    printed = cv2.copyMakeBorder(tag, quiet, quiet, quiet, quiet, cv2.BORDER_CONSTANT, value=255)
    grey = ink + (paper - ink) * (printed.astype(np.float32) / 255.0)
    return np.asarray(grey, dtype=np.float32)


def with_alpha(grey: Float32Array) -> Float32Array:
    """Return an opaque texture (N, M, 2) float32: premultiplied grey and alpha 1."""
    return np.dstack([grey, np.ones_like(grey)]).astype(np.float32)


def sample_bilinear(
    texture: Float32Array, col: Float32Array, row: Float32Array, *, border: str = 'replicate'
) -> Float32Array:
    """``texture`` (H, W[, C]) sampled at (col, row), shape S: (*S[, C]) float32."""
    if border not in ('replicate', 'transparent'):
        raise ValueError(f"border {border!r} must be 'replicate' or 'transparent'")
    if border == 'replicate':
        mode, value = cv2.BORDER_REPLICATE, (0.0, 0.0, 0.0, 0.0)
    else:
        mode, value = cv2.BORDER_CONSTANT, (0.0, 0.0, 0.0, 0.0)
    shape = np.shape(col)
    count = int(np.prod(shape))
    if count == 0:
        return np.zeros((*shape, *texture.shape[2:]), dtype=np.float32)
    if len(shape) == 2 and max(shape) < REMAP_WIDTH:
        map_col, map_row = (np.asarray(m, dtype=np.float32) for m in (col, row))
    else:
        width = REMAP_WIDTH if count > REMAP_WIDTH else max(count, 1)
        rows = -(-count // width)
        map_col, map_row = (
            np.resize(np.asarray(m, dtype=np.float32).ravel(), (rows, width)) for m in (col, row)
        )
    sample = cv2.remap(
        texture, map_col, map_row, cv2.INTER_LINEAR, borderMode=mode, borderValue=value
    )
    out = np.asarray(sample, dtype=np.float32)
    channels = out.shape[2:]
    if out.shape[:2] == shape:
        return out
    return out.reshape(-1, *channels)[:count].reshape((*shape, *channels))
