"""Re-identification of dropped tracks (``feature_tracker``'s active search): where a
prediction with a covariance expects a remembered track, its template is searched for inside
the 3-sigma ellipse by normalized cross-correlation (``feature_tracker``'s docstring)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from monoslam_shadow_node.core.feature_tracker import FloatArray, GrayImage, TrackerConfig

SEARCH_SIGMAS = 3.0
"""Re-identification searches the prediction's 3-sigma ellipse."""
TEMPLATE_MARGIN_PX = 4
"""A template is the LK window plus this much on each side (LK reads a pixel past it)."""


@dataclass(frozen=True)
class Search:
    """One image's re-identification: tracks brought back, searches made, predictions too
    uncertain to search, and held tracks a revived one displaced (crowded)."""

    revived: int = 0
    searched: int = 0
    unsearched: int = 0
    displaced: int = 0


def parabola_peak(values: NDArray[Any]) -> float:
    """Return the offset (-0.5 .. 0.5) of the peak of the parabola through three values
    around a maximum in the middle; 0 if they do not bend (or one is not finite)."""
    left, middle, right = (float(value) for value in values)
    bend = left - 2.0 * middle + right
    if not (math.isfinite(bend) and bend < 0.0):
        return 0.0
    return float(np.clip(0.5 * (left - right) / bend, -0.5, 0.5))


def search_region(
    config: TrackerConfig, shape: tuple[int, ...], pixel: FloatArray, covariance: FloatArray
) -> tuple[int, int, int, int] | str | None:
    """Return the integer centres (x0, y0, x1, y1) to try for a prediction: its 3-sigma
    box inside the image (past the border margin and the template's half-width);
    'too_wide' beyond reid_max_search_px; None for a prediction that is not finite,
    not positive definite or outside the image."""
    if not (np.all(np.isfinite(pixel)) and np.all(np.isfinite(covariance))):
        return None
    symmetric = 0.5 * (covariance + covariance.T)
    if symmetric[0, 0] <= 0 or np.linalg.det(symmetric) <= 0:
        return None
    half_x, half_y = SEARCH_SIGMAS * np.sqrt(np.diag(symmetric))
    if max(half_x, half_y) > config.reid_max_search_px:
        return 'too_wide'
    height, width = shape
    reach = max(config.border_margin_px, config.lk_window_px / 2.0)
    x0 = max(math.ceil(pixel[0] - half_x), math.ceil(reach))
    x1 = min(math.floor(pixel[0] + half_x), math.floor(width - 1 - reach))
    y0 = max(math.ceil(pixel[1] - half_y), math.ceil(reach))
    y1 = min(math.floor(pixel[1] + half_y), math.floor(height - 1 - reach))
    if x0 > x1 or y0 > y1:
        return None
    return x0, y0, x1, y1


def match_template(
    config: TrackerConfig,
    gray: GrayImage,
    template: GrayImage,
    pixel: FloatArray,
    covariance: FloatArray,
    region: tuple[int, int, int, int],
) -> tuple[float, float, float] | None:
    """Return the subpixel centre of the best normalized correlation of the template's
    core with ``gray`` over the centres of ``region`` inside the 3-sigma ellipse, and the
    correlation, if it reaches reid_min_ncc; else None."""
    x0, y0, x1, y1 = region
    window = config.lk_window_px
    core = template[TEMPLATE_MARGIN_PX : TEMPLATE_MARGIN_PX + window,
                    TEMPLATE_MARGIN_PX : TEMPLATE_MARGIN_PX + window]  # fmt: skip
    before = (window - 1) // 2  # the core's pixels left of (above) its centre
    after = window - 1 - before
    patch = gray[y0 - before : y1 + after + 1, x0 - before : x1 + after + 1]
    scores = cv2.matchTemplate(patch, np.ascontiguousarray(core), cv2.TM_CCOEFF_NORMED)
    scores = np.where(np.isfinite(scores), scores, -np.inf)
    xs = np.arange(x0, x1 + 1) - pixel[0]
    ys = np.arange(y0, y1 + 1) - pixel[1]
    information = np.linalg.inv(0.5 * (covariance + covariance.T))
    distance = (
        information[0, 0] * xs[None, :] ** 2
        + 2.0 * information[0, 1] * xs[None, :] * ys[:, None]
        + information[1, 1] * ys[:, None] ** 2
    )
    scores[distance > SEARCH_SIGMAS**2] = -np.inf
    row, column = np.unravel_index(int(np.argmax(scores)), scores.shape)
    if not scores[row, column] >= config.reid_min_ncc:
        return None
    du = (
        parabola_peak(scores[row, column - 1 : column + 2])
        if 0 < column < scores.shape[1] - 1
        else 0.0
    )
    dv = parabola_peak(scores[row - 1 : row + 2, column]) if 0 < row < scores.shape[0] - 1 else 0.0
    return x0 + column + du, y0 + row + dv, float(scores[row, column])
