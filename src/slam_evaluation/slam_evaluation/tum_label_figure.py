"""``tum_rgbd_sequence``'s figures (OpenCV): labels.png and masks.png."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from slam_core.arrays import FloatArray, IntArray
from slam_sim.core.depth_labels import LABEL_NAMES, MOVING, STATIC, UNKNOWN

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
    """Return a copy of the image (H, W, 3) with its tracks and a caption drawn."""
    canvas = np.ascontiguousarray(item.image.copy())
    for label in (UNKNOWN, STATIC, MOVING):  # movers on top
        for u, v in np.rint(item.pixels[item.labels == label]).astype(int).tolist():
            cv2.circle(canvas, (u, v), RADIUS_PX, COLOURS_BGR[label], -1, cv2.LINE_AA)
            cv2.circle(canvas, (u, v), RADIUS_PX, (0, 0, 0), 1, cv2.LINE_AA)
    counts = ', '.join(
        f'{int(np.count_nonzero(item.labels == code))} {LABEL_NAMES[code]}'
        for code in (MOVING, STATIC, UNKNOWN)
    )
    _caption(canvas, f'image {item.index}: {counts}')
    return canvas


@dataclass(frozen=True, eq=False)
class MaskedImage:
    """One mask to draw: rgb.txt indices of the image and of the depth map, the image
    (H, W, 3) uint8 BGR and the mask (H, W) int8."""

    index: int
    mask_index: int
    image: NDArray[np.uint8]
    mask: NDArray[np.int8]


def draw_mask(item: MaskedImage) -> NDArray[np.uint8]:
    """Return a copy of the image (H, W, 3) with the mask blended in and a caption."""
    canvas = item.image.astype(np.float64)
    for code, colour, alpha in ((MOVING, (0, 0, 255), 0.5), (UNKNOWN, (128, 128, 128), 0.35)):
        where = item.mask == code
        canvas[where] = (1.0 - alpha) * canvas[where] + alpha * np.asarray(colour, np.float64)
    out = np.ascontiguousarray(np.clip(np.rint(canvas), 0, 255).astype(np.uint8))
    shares = ', '.join(
        f'{100 * np.count_nonzero(item.mask == code) / item.mask.size:.1f} % {LABEL_NAMES[code]}'
        for code in (MOVING, UNKNOWN)
    )
    source = '' if item.mask_index == item.index else f' (mask of image {item.mask_index})'
    _caption(out, f'image {item.index}{source}: {shares}')
    return out


def _caption(canvas: NDArray[np.uint8], text: str) -> None:
    """Write ``text`` on a white bar at the top of ``canvas`` (in place)."""
    scale = min(0.6, canvas.shape[1] / 1100)  # the caption fits a 640 px wide image at 0.6
    width_px = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0]
    scale *= min(1.0, (canvas.shape[1] - 16) / max(width_px, 1))  # a longer one is shrunk
    bar_px = round(46 * scale)
    cv2.rectangle(canvas, (0, 0), (canvas.shape[1], bar_px), (255, 255, 255), -1)
    origin = (8, round(33 * scale))
    cv2.putText(canvas, text, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 1, cv2.LINE_AA)


def labels_png(items: Sequence[LabelledImage], columns: int = 2) -> bytes:
    """Return the PNG of the drawn images tiled ``columns`` per row; ValueError: see tiled_png."""
    if not items:
        raise ValueError('no image to draw')
    return tiled_png([draw_labels(item) for item in items], columns)


def masks_png(items: Sequence[MaskedImage], columns: int = 2) -> bytes:
    """Return the PNG of the drawn masks tiled ``columns`` per row; ValueError: see tiled_png."""
    if not items:
        raise ValueError('no mask to draw')
    return tiled_png([draw_mask(item) for item in items], columns)


def tiled_png(images: Sequence[NDArray[np.uint8]], columns: int = 2) -> bytes:
    """Return the PNG bytes of ``images`` tiled ``columns`` per row; ValueError for no image,
    sizes that differ or a failed encoding."""
    if not images:
        raise ValueError('no image to draw')
    shape = images[0].shape
    if any(tile.shape != shape for tile in images):
        raise ValueError('the images to draw differ in size')
    rows = -(-len(images) // columns)
    tiles = [*images, *[np.full(shape, 255, dtype=np.uint8)] * (rows * columns - len(images))]
    grid = np.vstack([np.hstack(tiles[r * columns : (r + 1) * columns]) for r in range(rows)])
    ok, data = cv2.imencode('.png', grid)
    if not ok:
        raise ValueError('OpenCV could not encode the figure as PNG')
    return bytes(data.tobytes())
