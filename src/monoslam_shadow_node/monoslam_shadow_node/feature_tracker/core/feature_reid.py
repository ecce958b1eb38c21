"""Re-identification of dropped tracks (``feature_tracker``'s active search): where a
prediction with a covariance expects a remembered track, its template, warped to the
predicted view when the prediction brings a warp, is searched for inside the 3-sigma ellipse
by normalized cross-correlation, and its best places are aligned by an affine map and
checked (``feature_tracker``'s docstring).

Look-alikes. A 3-sigma ellipse after the camera was away is wide (20-30 px sigma), and
several places in it may look like the template (corners of rectangles of one grey). Much of
a returning feature's prediction error is the drift the camera gathered while away (the old
map seen from a pose that drifted), which the old map's features share: the tracks that came
back earlier (held now, with their predictions) and this image's unique matches show it as a
common shift of found against predicted pixels. (The far side's features, from which the
camera's pose was estimated, do not show it: they drifted with the camera.) Where at least
``SHIFT_MIN_MATCHES`` agree, a search with several places takes the one place within 3 sigma
of its prediction moved by their median shift, sigma being their spread about it (at least a
match's own ``TRACKING_SIGMA_PX``), if only one lies there. Each map point has its own error
too (its depth), so this shift only decides between look-alikes and never narrows a search:
a few matches' spread says little of another point's.

The image's motion. A prediction made before the image is seen carries the camera's motion
noise over one frame (a hand-held camera's turn: 25-35 px sigma at 30 Hz), the same for
every point, and a 3-sigma ellipse that wide is not searched (``reid_max_search_px``). The
tracks carried into the image with a prediction show how the image actually moved:
``aligned_predictions`` fits an affine map of their predicted pixels onto their tracked
ones (at least ``MOTION_MIN_TRACKS``, one reweighting that drops those beyond
``SEARCH_SIGMAS`` robust sigma), moves each remembered track's prediction through it, and
takes as its covariance the spread of the carried tracks about the fit (at least
``TRACKING_SIGMA_PX``) plus the part of its own covariance above the carried tracks'
median one (its own error: an uncertain depth), when that is smaller than the prediction's
and the prediction is too wide to search as it is; one that can be searched keeps its own
covariance (a returning map feature's error is its old map's drift, which SLAM's covariance
may not hold and the carried tracks do not show)."""

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
"""The smallest searched core: a warp that shrinks the template more than this leaves (the
feature is seen from much farther than where its template was captured) is not searched."""
MAX_WARP_STRETCH = 4.0
"""A warp stretching one direction more than this relative to the other (a patch seen nearly
edge-on) is not searched."""
CANDIDATES = 5
"""The highest local maxima of a search's correlation that are aligned and checked
(``find_peaks``); more look-alikes than this in one ellipse leave it undecided anyway."""
SAME_PLACE_PX = 2.0
"""Candidates aligned to within this of each other are one place (two maxima of one blob)."""
REFINE_MARGIN_PX = 3
"""How far the affine alignment may move a candidate's centre (its local maximum lies
within a pixel of the true centre; the rest is the foreshortening's shift of the peak)."""
MAX_REFINE_SCALE = 2.0
"""The most the alignment may scale the warped template along any direction (beyond,
it is no longer the same view of the patch)."""
REFINE_ITERATIONS = 50
"""Iterations of the affine alignment (it converges in a few from a pixel off)."""
SHIFT_MIN_MATCHES = 3
"""Unique matches in an image needed to decide look-alikes by their shared shift
(``resolve_by_shift``): their median tolerates one wrong match."""
TRACKING_SIGMA_PX = 1.0
"""The smallest spread assumed about the shared shift: a match's own error (subpixel
correlation peak, the tracker's 1 px)."""
RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))
"""The median of the length of a 2-D offset with independent unit-sigma axes: divides the
median residual into a per-axis sigma."""


@dataclass(frozen=True)
class Search:
    """One image's re-identification: tracks brought back (of them ``resolved``: among
    look-alikes, decided by the image's shared shift), searches made, predictions not
    searched (too uncertain, or a template warped past recognition: ``search_core``),
    held tracks a revived one displaced (crowded), and candidates left without an alignment
    (``Alignments``)."""

    revived: int = 0
    searched: int = 0
    unsearched: int = 0
    displaced: int = 0
    resolved: int = 0
    unaligned: int = 0


@dataclass
class Alignments:
    """One image's budget of ``refine_match`` alignments (the tracker's
    ``reid_max_alignments``): those still allowed, and the candidates refused one. They go
    in the predictions' order (SLAM sends its features oldest first: a depth start's points
    before all). One costs about 3 ms (up to ``REFINE_ITERATIONS`` of enhanced correlation
    on the core, profiled on Bonn crowd), and the tracker's other work 10-15 ms of a 30 Hz
    image's 33 (bench/README.md): unbounded, searching every remembered track in view took
    110 ms an image there. A peak that matches as it is needs no alignment and is always
    taken."""

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


@dataclass(frozen=True)
class Peak:
    """A place where the template matches: its centre (u, v) px, subpixel, and the
    correlation of the template aligned there (``refine_match``)."""

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
    """Return the places inside the 3-sigma ellipse where ``core`` (a square patch,
    ``search_core``) matches ``gray``, best first: the ``CANDIDATES`` highest local maxima of
    the normalized correlation over the centres of ``region`` inside the ellipse (not on the
    search's border or the ellipse's rim, where the true peak may lie beyond) that reach
    reid_min_ncc as they are (refined to subpixel by a parabola through the peak) or aligned
    by ``refine_match``; candidates within ``SAME_PLACE_PX`` of a better one are the same
    place. (The alignment is only for those below: on a patch with little texture it may
    slide to a shrunken fit elsewhere, which it refuses, losing a match that was there.)
    ``alignments`` (None: no limit) is spent one per alignment; once it is spent the
    candidates below reid_min_ncc are left, and counted."""
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
    """Return the match of ``core`` centred near pixel (x, y) of ``gray`` after aligning it
    by an affine map (enhanced correlation, cv2.findTransformECC, starting from a pure shift):
    its subpixel centre and the correlation it reaches. The template's warp is SLAM's
    first-order guess for a plane facing the camera that first saw the point; the surface's
    true slant foreshortens it further, which the affine alignment takes up, as Shi and
    Tomasi monitor features under an affine model. None where the alignment does not
    converge, moves the centre more than ``REFINE_MARGIN_PX`` or scales the core by more than
    ``MAX_REFINE_SCALE`` either way."""
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
    """Return the shift (2,) px that found pixels (N, 2) share against their predictions
    (N, 2), their median, and the radius that holds a match about it: ``SEARCH_SIGMAS``
    sigma of their spread (at least ``TRACKING_SIGMA_PX``); None with fewer than
    ``SHIFT_MIN_MATCHES`` (module docstring)."""
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
    """Return the predictions' pixels (K, 2) and covariances (K, 2, 2) of ``ids`` (K,) moved
    by the image's motion (module docstring); ``rows`` maps each track carried into this
    image to its row of ``tracked`` (N, 2), its pixel now. A covariance is narrowed only
    where its ``SEARCH_SIGMAS`` half-axis exceeds ``narrow_beyond_px`` (the tracker's
    reid_max_search_px: too wide to search as it is); one that can be searched keeps it, as
    a returning map feature's error is its old map's drift, which the carried tracks do not
    show. Unchanged with fewer than ``MOTION_MIN_TRACKS`` usable carried tracks."""
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
    """Decide look-alikes by the shift the image's matches share (their predicted (N, 2) and
    found (N, 2) pixels, ``shared_shift``): each ``pending`` search (its predicted pixel and
    peaks) takes the one peak within the radius of its prediction moved by the shift, if
    exactly one lies there; else None (as for all without a shift)."""
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
    """Search ``gray`` for the remembered ``templates`` (id -> template) that the
    ``predictions`` (ids (K,), pixels (K, 2), covariances (K, 2, 2), warps (K, 2, 2)) expect
    in view; return what was found, (id, u, v, correlation) each, and the counts (revived:
    all found): the unique matches (one place: ``find_peaks``), then the look-alikes decided by the
    shift that they and the ``held`` tracks that came back earlier (their predicted and
    tracked pixels, (H, 2) each) share (``resolve_by_shift``)."""
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
