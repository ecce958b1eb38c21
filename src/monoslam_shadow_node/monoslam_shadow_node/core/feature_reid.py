"""Re-identification of dropped tracks (``feature_tracker``'s active search): where a
prediction with a covariance expects a remembered track, its template, warped to the
predicted view when the prediction brings a warp, is searched for inside the 3-sigma ellipse
by normalized cross-correlation (``feature_tracker``'s docstring)."""

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
MIN_CORE_PX = 9
"""The smallest searched core: a warp that shrinks the template more than this leaves (the
feature is seen from much farther than where its template was captured) is not searched."""
MAX_WARP_STRETCH = 4.0
"""A warp stretching one direction more than this relative to the other (a patch seen nearly
edge-on) is not searched."""


@dataclass(frozen=True)
class Search:
    """One image's re-identification: tracks brought back, searches made, predictions not
    searched (too uncertain, or a template warped past recognition: ``search_core``), and
    held tracks a revived one displaced (crowded)."""

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


def search_core(template: GrayImage, window: int, warp: FloatArray | None) -> GrayImage | None:
    """Return the patch to search for: the template's central ``window`` x ``window`` core,
    or, for a warp A (2, 2) = d(pixel now)/d(pixel in the template) that is finite and
    orientation-preserving, the template resampled through A (bilinear) onto the largest
    odd-sided square up to ``window`` that it still covers; None for a warp that shrinks it
    below ``MIN_CORE_PX`` or stretches it beyond ``MAX_WARP_STRETCH`` (no search). A zero or
    absent warp means none is known: the core as it is."""
    if warp is None or not np.any(warp):
        return template[TEMPLATE_MARGIN_PX : TEMPLATE_MARGIN_PX + window,
                        TEMPLATE_MARGIN_PX : TEMPLATE_MARGIN_PX + window]  # fmt: skip
    if not (np.all(np.isfinite(warp)) and np.linalg.det(warp) > 0.0):
        return None
    smallest, largest = np.linalg.svd(warp, compute_uv=False)[::-1]
    if largest > MAX_WARP_STRETCH * smallest:
        return None
    half = min((window - 1) // 2, math.floor(smallest * (template.shape[0] - 1) / 2.0))
    if 2 * half + 1 < MIN_CORE_PX:
        return None
    source = (template.shape[0] - 1) / 2.0
    affine = np.column_stack([warp, [half, half] - warp @ [source, source]])
    side = 2 * half + 1
    warped = cv2.warpAffine(
        template, affine, (side, side), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    return np.asarray(warped, dtype=np.uint8)


def match_template(
    config: TrackerConfig,
    gray: GrayImage,
    core: GrayImage,
    pixel: FloatArray,
    covariance: FloatArray,
    region: tuple[int, int, int, int],
) -> tuple[float, float, float] | None:
    """Return the subpixel centre of the best normalized correlation of ``core`` (a square
    patch, ``search_core``) with ``gray`` over the centres of ``region`` inside the 3-sigma
    ellipse, and the correlation, if it reaches reid_min_ncc at a peak inside the ellipse (not
    on the search's border or rim, where the true peak may lie beyond) and is unique; else
    None. Unique: the centres reaching reid_min_ncc form one connected peak. A second one is
    another place that looks the same (the corner of another rectangle of the same grey, a
    repeated pattern): which one is the feature the image cannot say, and a wrong choice
    would feed SLAM a false loop closure; a later image, with a smaller ellipse, may decide."""
    x0, y0, x1, y1 = region
    window = core.shape[0]
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
    rows, columns = scores.shape
    if not (0 < row < rows - 1 and 0 < column < columns - 1):
        return None  # on the border of the search: the peak may lie beyond it
    neighbours = scores[row - 1 : row + 2, column - 1 : column + 2]
    if not np.all(np.isfinite(neighbours)):
        return None  # on the ellipse's rim: likewise
    passing = np.ascontiguousarray(scores >= config.reid_min_ncc, dtype=np.uint8)
    if cv2.connectedComponents(passing, connectivity=8)[0] > 2:  # the background and one peak
        return None  # ambiguous: another place matches as well
    du = parabola_peak(scores[row, column - 1 : column + 2])
    dv = parabola_peak(scores[row - 1 : row + 2, column])
    return x0 + column + du, y0 + row + dv, float(scores[row, column])


def make_room(
    track_ids: NDArray[np.int64],
    ages: NDArray[np.int64],
    revived: NDArray[np.bool_],
    mapped: NDArray[np.int64],
    scores: FloatArray,
    excess: int,
) -> tuple[NDArray[np.bool_], int]:
    """Return which of the tracks (N,) leave so that ``excess`` fewer remain (max_features),
    and how many of those are held tracks: first the youngest held tracks that are not map
    features (ids not in ``mapped``, the predicted ones: a map feature found again is worth
    more than a track no filter has mapped), then the ``revived`` with the lowest
    correlation ``scores`` (back to sleep)."""
    out = np.zeros(len(track_ids), dtype=bool)
    spare = np.flatnonzero(~revived & ~np.isin(track_ids, mapped))
    spare = spare[np.argsort(ages[spare], kind='stable')][:excess]
    out[spare] = True
    rest = excess - len(spare)
    if rest > 0:
        rows = np.flatnonzero(revived)
        out[rows[np.argsort(scores[rows], kind='stable')][:rest]] = True
    return out, len(spare)
