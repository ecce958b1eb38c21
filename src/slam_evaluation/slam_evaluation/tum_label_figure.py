"""The labels PNG of ``tum_rgbd_sequence``: the tracks of a few colour images drawn over them
in their depth label's colour (moving red, static green, unknown grey), tiled two per row
with each image's counts written on it (OpenCV)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from slam_sim.core.depth_labels import LABEL_NAMES, MOVING, STATIC, UNKNOWN

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
COLOURS_BGR = {MOVING: (0, 0, 255), STATIC: (0, 200, 0), UNKNOWN: (170, 170, 170)}
RADIUS_PX = 5


@dataclass(frozen=True, eq=False)
class LabelledImage:
    """One image to draw: its index in rgb.txt, the colour image (H, W, 3) uint8 BGR, and its
    tracks' raw pixels (N, 2) with their label codes (N,)."""

    index: int
    image: NDArray[np.uint8]
    pixels: FloatArray
    labels: IntArray


def draw_labels(item: LabelledImage) -> NDArray[np.uint8]:
    """Return a copy of the image (H, W, 3) with its tracks drawn (filled discs in the label
    colours, black rims) and a caption with the image index and the counts."""
    canvas = np.ascontiguousarray(item.image.copy())
    for label in (UNKNOWN, STATIC, MOVING):  # movers on top
        for u, v in np.rint(item.pixels[item.labels == label]).astype(int).tolist():
            cv2.circle(canvas, (u, v), RADIUS_PX, COLOURS_BGR[label], -1, cv2.LINE_AA)
            cv2.circle(canvas, (u, v), RADIUS_PX, (0, 0, 0), 1, cv2.LINE_AA)
    counts = ', '.join(
        f'{int(np.count_nonzero(item.labels == code))} {LABEL_NAMES[code]}'
        for code in (MOVING, STATIC, UNKNOWN)
    )
    caption = f'image {item.index}: {counts}'
    scale = min(0.6, canvas.shape[1] / 1100)  # the caption fits a 640 px wide image at 0.6
    bar_px = round(46 * scale)
    cv2.rectangle(canvas, (0, 0), (canvas.shape[1], bar_px), (255, 255, 255), -1)
    origin = (8, round(33 * scale))
    cv2.putText(
        canvas, caption, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 1, cv2.LINE_AA
    )
    return canvas


def labels_png(items: Sequence[LabelledImage], columns: int = 2) -> bytes:
    """Return the PNG bytes of the drawn images (``draw_labels``) tiled ``columns`` per row
    (images of one size; an empty tile is white).

    Raises:
        ValueError: no image, images of different sizes, or OpenCV cannot encode the PNG.

    """
    if not items:
        raise ValueError('no image to draw')
    tiles = [draw_labels(item) for item in items]
    shape = tiles[0].shape
    if any(tile.shape != shape for tile in tiles):
        raise ValueError('the images to draw differ in size')
    rows = -(-len(tiles) // columns)
    tiles += [np.full(shape, 255, dtype=np.uint8)] * (rows * columns - len(tiles))
    grid = np.vstack([np.hstack(tiles[r * columns : (r + 1) * columns]) for r in range(rows)])
    ok, data = cv2.imencode('.png', grid)
    if not ok:
        raise ValueError('OpenCV could not encode the labels figure as PNG')
    return bytes(data.tobytes())
