"""Re-identification of dropped tracks: a remembered template searched for inside its
prediction's 3-sigma ellipse by correlation, aligned by an affine map and checked.

Design notes: docs/design/shadow_filter_core.md."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from monoslam_shadow_node.feature_tracker.core.feature_config import GrayImage, TrackerConfig
from slam_core.arrays import FloatArray

SEARCH_SIGMAS = 3.0
"""Re-identification searches the prediction's 3-sigma ellipse."""
TEMPLATE_MARGIN_PX = 4
"""A template is the LK window plus this much on each side (LK reads a pixel past it)."""
MIN_CORE_PX = 9
"""The smallest searched core, px: a warp that shrinks the template below it is not searched."""
MAX_WARP_STRETCH = 4.0
"""A warp stretching one direction more than this times the other is not searched."""
CANDIDATES = 5
"""The highest local maxima of a search's correlation that are checked (``find_peaks``)."""
SAME_PLACE_PX = 2.0
"""Candidates aligned to within this of each other are one place (two maxima of one blob)."""
REFINE_MARGIN_PX = 3
"""How far the affine alignment may move a candidate's centre, px."""
MAX_REFINE_SCALE = 2.0
"""The most the alignment may scale the warped template along any direction."""
REFINE_ITERATIONS = 50
"""Iterations of the affine alignment (it converges in a few from a pixel off)."""
SHIFT_MIN_MATCHES = 3
"""Unique matches in an image needed to decide look-alikes by their shared shift."""
TRACKING_SIGMA_PX = 1.0
"""The smallest spread assumed about the shared shift: a match's own error, px."""
RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))
"""The median of the length of a 2-D offset with independent unit-sigma axes: divides the
median residual into a per-axis sigma."""


@dataclass(frozen=True)
class Search:
    """One image's re-identification counts (as ``feature_types.TrackCounts``)."""

    revived: int = 0
    searched: int = 0
    unsearched: int = 0
    displaced: int = 0
    resolved: int = 0
    unaligned: int = 0


@dataclass
class Alignments:
    """One image's budget of ``refine_match`` alignments: those left, candidates refused."""

    left: int
    refused: int = 0

    def take(self) -> bool:
        """Spend one alignment if any is left (True), else count a refused candidate."""
        if self.left > 0:
            self.left -= 1
            return True
        self.refused += 1
        return False


def parabola_peak(values: NDArray[Any]) -> float:
    """Return the peak offset (-0.5 .. 0.5) of the parabola through three values; 0 if flat."""
    left, middle, right = (float(value) for value in values)
    bend = left - 2.0 * middle + right
    if not (math.isfinite(bend) and bend < 0.0):
        return 0.0
    return float(np.clip(0.5 * (left - right) / bend, -0.5, 0.5))


def search_region(
    config: TrackerConfig, shape: tuple[int, ...], pixel: FloatArray, covariance: FloatArray
) -> tuple[int, int, int, int] | str | None:
    """Return the centres (x0, y0, x1, y1) px to try for a prediction, 'too_wide', or None
    (not finite, not positive definite, or outside the image)."""
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
    """Return the square patch to search for, the template's core warped by ``warp`` (2, 2)
    (zero or None: unwarped); None for a warp past recognition."""
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


@dataclass(frozen=True)
class Peak:
    """A place where the template matches: centre (u, v) px and its correlation."""

    u: float
    v: float
    ncc: float


def find_peaks(
    config: TrackerConfig,
    gray: GrayImage,
    core: GrayImage,
    pixel: FloatArray,
    covariance: FloatArray,
    region: tuple[int, int, int, int],
    alignments: Alignments | None = None,
) -> list[Peak]:
    """Return the places in the 3-sigma ellipse of ``pixel`` (2,), ``covariance`` (2, 2) px^2
    where ``core`` matches ``gray``, best first (``alignments`` None: no limit)."""
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
    inside = np.isfinite(scores)
    local = scores == ndimage.maximum_filter(scores, size=3, mode='constant', cval=-np.inf)
    local &= ndimage.minimum_filter(inside, size=3, mode='constant', cval=False)
    rows, columns = np.nonzero(local)
    order = np.argsort(-scores[rows, columns], kind='stable')[:CANDIDATES]
    peaks: list[Peak] = []
    for row, column in zip(rows[order].tolist(), columns[order].tolist(), strict=True):
        score = float(scores[row, column])
        if score >= config.reid_min_ncc:  # matches as it is: the subpixel peak of the shift
            du = parabola_peak(scores[row, column - 1 : column + 2])
            dv = parabola_peak(scores[row - 1 : row + 2, column])
            peak: Peak | None = Peak(x0 + column + du, y0 + row + dv, score)
        elif alignments is None or alignments.take():
            peak = refine_match(gray, core, x0 + column, y0 + row)
        else:
            continue
        if peak is None or peak.ncc < config.reid_min_ncc:
            continue
        if all(math.hypot(peak.u - p.u, peak.v - p.v) > SAME_PLACE_PX for p in peaks):
            peaks.append(peak)
    return sorted(peaks, key=lambda peak: -peak.ncc)


def refine_match(gray: GrayImage, core: GrayImage, x: int, y: int) -> Peak | None:
    """Return the match of ``core`` near pixel (x, y) of ``gray`` after an affine alignment;
    None where it fails or goes beyond ``REFINE_MARGIN_PX`` or ``MAX_REFINE_SCALE``."""
    window = core.shape[0]
    half = (window - 1) / 2.0
    side = window + 2 * REFINE_MARGIN_PX
    source = cv2.getRectSubPix(gray, (side, side), (float(x), float(y)))
    start = np.array([[1.0, 0.0, REFINE_MARGIN_PX], [0.0, 1.0, REFINE_MARGIN_PX]], np.float32)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, REFINE_ITERATIONS, 1e-4)
    try:
        everywhere = np.ones(source.shape, np.uint8)  # every pixel of the source is valid
        correlation, warp = cv2.findTransformECC(
            core.astype(np.float32), source.astype(np.float32), start, cv2.MOTION_AFFINE,
            criteria, everywhere, 1,
        )  # fmt: skip
    except cv2.error:  # did not converge, or a flat patch
        return None
    linear = warp[:, :2].astype(np.float64)
    smallest, largest = np.linalg.svd(linear, compute_uv=False)[::-1]
    if not (smallest >= 1.0 / MAX_REFINE_SCALE and largest <= MAX_REFINE_SCALE):
        return None
    centre = linear @ [half, half] + warp[:, 2] - (side - 1) / 2.0  # offset from (x, y)
    if not (np.all(np.isfinite(centre)) and float(np.hypot(*centre)) <= REFINE_MARGIN_PX):
        return None
    return Peak(x + float(centre[0]), y + float(centre[1]), float(correlation))


def shared_shift(predicted: FloatArray, matched: FloatArray) -> tuple[FloatArray, float] | None:
    """Return the median shift (2,) px of ``matched`` (N, 2) against ``predicted`` (N, 2) and
    the radius px that holds a match about it; None with too few matches."""
    if len(matched) < SHIFT_MIN_MATCHES:
        return None
    offsets = np.asarray(matched, np.float64) - np.asarray(predicted, np.float64)
    shift = np.median(offsets, axis=0)
    spread = float(np.median(np.linalg.norm(offsets - shift, axis=1))) / RAYLEIGH_MEDIAN
    return shift, SEARCH_SIGMAS * max(TRACKING_SIGMA_PX, spread)


MOTION_MIN_TRACKS = 8
"""Carried tracks needed to fit the image's motion (an affine map: 6 unknowns)."""


def _affine_fit(source: FloatArray, target: FloatArray) -> FloatArray:
    """Least-squares affine map (2, 3) of pixels ``source`` (N, 2) onto ``target`` (N, 2)."""
    design = np.column_stack([source, np.ones(len(source))])
    solution, *_ = np.linalg.lstsq(design, target, rcond=None)
    return np.asarray(solution.T, dtype=np.float64)


def aligned_predictions(
    pixels: FloatArray,
    covariances: FloatArray,
    ids: NDArray[np.int64],
    rows: dict[int, int],
    tracked: NDArray[np.float32],
    narrow_beyond_px: float = 0.0,
) -> tuple[FloatArray, FloatArray]:
    """Return the pixels (K, 2) and covariances (K, 2, 2) of predictions ``ids`` (K,) moved by
    the image's motion; ``rows``: carried track id -> row of ``tracked`` (N, 2)."""
    pixels = np.asarray(pixels, np.float64)
    covariances = np.asarray(covariances, np.float64)
    carried = np.array([i in rows for i in ids.tolist()], dtype=bool).reshape(-1)
    finite = np.all(np.isfinite(pixels), axis=1)
    usable = carried & finite & (covariances[:, 0, 0] > 0.0)
    if np.count_nonzero(usable) < MOTION_MIN_TRACKS:
        return pixels, covariances
    source = pixels[usable]
    target = np.asarray(tracked, np.float64)[[rows[i] for i in ids[usable].tolist()]]
    inliers = np.ones(len(source), dtype=bool)
    for _ in range(2):  # a fit, then a fit without the tracks beyond 3 robust sigma of it
        affine = _affine_fit(source[inliers], target[inliers])
        distance = np.linalg.norm(target - (source @ affine[:, :2].T + affine[:, 2]), axis=1)
        sigma = float(np.median(distance[inliers])) / RAYLEIGH_MEDIAN
        inliers = distance <= SEARCH_SIGMAS * max(sigma, TRACKING_SIGMA_PX)
        if np.count_nonzero(inliers) < MOTION_MIN_TRACKS:
            return pixels, covariances
    residual = target[inliers] - (source[inliers] @ affine[:, :2].T + affine[:, 2])
    dof = max(len(residual) - 3, 1)  # 6 unknowns over 2 coordinates
    spread = residual.T @ residual / dof + TRACKING_SIGMA_PX**2 * np.eye(2)
    typical = np.median(covariances[usable], axis=0)
    out_pixels, out_covariances = pixels.copy(), covariances.copy()
    for k in np.flatnonzero(~carried & finite & (covariances[:, 0, 0] > 0.0)).tolist():
        excess = covariances[k] - typical  # its own error: what it has above the others
        values, vectors = np.linalg.eigh(0.5 * (excess + excess.T))
        narrowed = spread + (vectors * np.clip(values, 0.0, None)) @ vectors.T
        if np.trace(narrowed) < np.trace(covariances[k]):
            out_pixels[k] = affine[:, :2] @ pixels[k] + affine[:, 2]
            half_axis = SEARCH_SIGMAS * math.sqrt(np.max(np.diag(covariances[k])))
            if half_axis > narrow_beyond_px:
                out_covariances[k] = narrowed
    return out_pixels, out_covariances


def resolve_by_shift(
    predicted: FloatArray, matched: FloatArray, pending: list[tuple[FloatArray, list[Peak]]]
) -> list[Peak | None]:
    """Return per ``pending`` search the one peak near its prediction moved by the shift the
    matches share (``shared_shift``), or None."""
    shared = shared_shift(predicted, matched)
    if shared is None:
        return [None] * len(pending)
    shift, radius = shared
    out: list[Peak | None] = []
    for pixel, peaks in pending:
        expected = np.asarray(pixel, np.float64) + shift
        near = [p for p in peaks if math.hypot(p.u - expected[0], p.v - expected[1]) <= radius]
        out.append(near[0] if len(near) == 1 else None)
    return out


def search_predicted(
    config: TrackerConfig,
    gray: GrayImage,
    templates: dict[int, GrayImage],
    predictions: tuple[NDArray[np.int64], FloatArray, FloatArray, FloatArray],
    held: tuple[FloatArray, FloatArray],
) -> tuple[list[tuple[int, float, float, float]], Search]:
    """Search ``gray`` for ``templates`` where ``predictions`` (ids (K,), pixels (K, 2),
    covariances and warps (K, 2, 2)) expect them, ``held``: predicted and tracked pixels
    (H, 2) of tracks back earlier; return (id, u, v, ncc) found, and the counts."""
    found: list[tuple[int, float, float, float]] = []
    expected: list[FloatArray] = []
    pending: list[tuple[int, FloatArray, list[Peak]]] = []
    searched = unsearched = 0
    alignments = Alignments(config.reid_max_alignments)
    ids, pixels, covariances, warps = predictions
    for track_id, pixel, covariance, warp in zip(
        ids.tolist(), pixels, covariances, warps, strict=True
    ):
        if track_id not in templates:
            continue
        region = search_region(config, gray.shape, pixel, covariance)
        if region is None:
            continue
        core = search_core(templates[track_id], config.lk_window_px, warp)
        if isinstance(region, str) or core is None:  # 'too_wide', or too far from it
            unsearched += 1
            continue
        searched += 1
        peaks = find_peaks(config, gray, core, pixel, covariance, region, alignments)
        if len(peaks) == 1:
            found.append((track_id, peaks[0].u, peaks[0].v, peaks[0].ncc))
            expected.append(pixel)
        elif len(peaks) > 1:
            pending.append((track_id, pixel, peaks))
    unique = np.array([item[1:3] for item in found]).reshape(-1, 2)
    decided = resolve_by_shift(
        np.concatenate([held[0], np.array(expected).reshape(-1, 2)]),
        np.concatenate([held[1], unique]),
        [(pixel, peaks) for _, pixel, peaks in pending],
    )
    for (track_id, _, _), peak in zip(pending, decided, strict=True):
        if peak is not None:
            found.append((track_id, peak.u, peak.v, peak.ncc))
    resolved = len(found) - len(unique)
    return found, Search(len(found), searched, unsearched, 0, resolved, alignments.refused)


def make_room(
    track_ids: NDArray[np.int64],
    ages: NDArray[np.int64],
    revived: NDArray[np.bool_],
    mapped: NDArray[np.int64],
    scores: FloatArray,
    excess: int,
) -> tuple[NDArray[np.bool_], int]:
    """Return which tracks (N,) leave so that ``excess`` fewer remain, and how many of them
    are held (not ``revived``) tracks."""
    out = np.zeros(len(track_ids), dtype=bool)
    spare = np.flatnonzero(~revived & ~np.isin(track_ids, mapped))
    spare = spare[np.argsort(ages[spare], kind='stable')][:excess]
    out[spare] = True
    rest = excess - len(spare)
    if rest > 0:
        rows = np.flatnonzero(revived)
        out[rows[np.argsort(scores[rows], kind='stable')][:rest]] = True
    return out, len(spare)
