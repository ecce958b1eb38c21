"""Image feature tracking for the monocular SLAM front end (ROS-free): LK tracking with
checks, re-identification of dropped tracks, detection where tracks are missing.

Ids are int64 from 1, never reused; pixels are raw (distorted), OpenCV's convention; nothing
returned is NaN. Design notes: docs/design/shadow_filter_core.md."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from monoslam_shadow_node.feature_tracker.core.feature_config import (
    GrayImage,
    GrayStack,
    TrackerConfig,
)
from monoslam_shadow_node.feature_tracker.core.feature_detection import (
    CornerDetector,
    crowded_tracks,
)
from monoslam_shadow_node.feature_tracker.core.feature_reid import (
    TEMPLATE_MARGIN_PX,
    Search,
    aligned_predictions,
    make_room,
    search_predicted,
)
from monoslam_shadow_node.feature_tracker.core.feature_types import (
    DROP_REASONS,
    Predictions,
    TrackCounts,
    TrackedFeatures,
)
from slam_core.arrays import FloatArray, IntArray


def as_gray_image(image: object) -> GrayImage:
    """Return ``image`` as C-contiguous (H, W) uint8; ValueError unless non-empty 2-D uint8."""
    if not isinstance(image, np.ndarray) or image.ndim != 2 or image.dtype != np.uint8:
        what = f'{image.ndim}-D {image.dtype}' if isinstance(image, np.ndarray) else type(image)
        raise ValueError(f'the tracker takes 2-D uint8 (gray) images, got {what}')
    if image.size == 0:
        raise ValueError(f'empty image ({image.shape[1]}x{image.shape[0]} px)')
    return np.ascontiguousarray(image)


class FeatureTracker:
    """Detects and tracks features image after image."""

    def __init__(self, config: TrackerConfig | None = None) -> None:
        self.config = config if config is not None else TrackerConfig()
        self._next_id = 1
        self._previous: GrayImage | None = None
        self._ids: IntArray = np.zeros(0, np.int64)
        self._pixels = np.zeros((0, 2), np.float32)
        self._ages: IntArray = np.zeros(0, np.int64)
        self._side = self.config.lk_window_px + 2 * TEMPLATE_MARGIN_PX
        self._templates: GrayStack = np.zeros((0, self._side, self._side), np.uint8)
        self._images = 0
        self._pending_reset = 0
        self._detector = CornerDetector(self.config)
        self._dormant: dict[int, tuple[GrayImage, int]] = {}  # id -> (template, age)
        self._returned: set[int] = set()  # held tracks that came back by re-identification
        self._mapped: set[int] = set()  # ids of the latest predictions: the SLAM map's features

    @property
    def next_id(self) -> int:
        """The id the next new track gets."""
        return self._next_id

    @property
    def track_count(self) -> int:
        """Tracks held (those of the last image)."""
        return len(self._ids)

    def reset(self) -> int:
        """Drop every track (ids go on); return how many (counted as ``reset`` next image)."""
        dropped = len(self._ids)
        self._pending_reset += dropped
        self._clear()
        self._dormant.clear()  # another camera: the templates no longer apply
        self._mapped.clear()
        return dropped

    def track(self, image: object, predictions: Predictions | None = None) -> TrackedFeatures:
        """Return the features of ``image`` (H, W) uint8. Raises ValueError for another image
        (the tracker unchanged)."""
        gray = as_gray_image(image)
        drops = dict.fromkeys(DROP_REASONS, 0)
        if self._previous is not None and self._previous.shape != gray.shape:
            self.reset()
        drops['reset'], self._pending_reset = self._pending_reset, 0
        if predictions is not None:  # SLAM predicts every feature of its map (in view or not)
            self._mapped = set(np.asarray(predictions.ids).reshape(-1).tolist())
        tracked = predicted = 0
        if self._previous is not None and len(self._ids):
            predicted = self._follow(self._previous, gray, predictions, drops)
            tracked = len(self._ids)
        search = self._revive(gray, predictions)
        tracked -= search.displaced
        drops['crowded'] += search.displaced
        new = 0
        due = self._images % self.config.detect_every_n_frames == 0 or not len(self._ids)
        if due and len(self._ids) < self.config.max_features:
            new = self._detect(gray)
        self._previous = gray
        self._images += 1
        return TrackedFeatures(
            self._ids.copy(),
            self._pixels.astype(np.float64),
            self._ages.copy(),
            TrackCounts(
                tracked=tracked,
                predicted=predicted,
                new=new,
                revived=search.revived,
                searched=search.searched,
                unsearched=search.unsearched,
                unaligned=search.unaligned,
                resolved=search.resolved,
                **drops,
            ),
        )

    # --- tracking ---------------------------------------------------------------------------

    def _lk(
        self,
        before: GrayImage,
        after: GrayImage,
        start: NDArray[np.float32],
        guess: NDArray[np.float32],
        levels: int | None = None,
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_], NDArray[np.float32]]:
        """Return LK's end pixels (M, 2), status (M,) and errors (M,) of ``start`` (M, 2)."""
        config = self.config
        end, status, error = cv2.calcOpticalFlowPyrLK(
            before,
            after,
            start.reshape(-1, 1, 2),
            guess.reshape(-1, 1, 2).copy(),
            winSize=(config.lk_window_px, config.lk_window_px),
            maxLevel=config.lk_pyramid_levels if levels is None else levels,
            criteria=(
                cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT,
                config.lk_max_iterations,
                config.lk_epsilon_px,
            ),
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        return (
            np.asarray(end, np.float32).reshape(-1, 2),
            np.asarray(status).reshape(-1) != 0,
            np.asarray(error, np.float32).reshape(-1),
        )

    def _guesses(
        self, predictions: Predictions | None, shape: tuple[int, ...]
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_], NDArray[np.bool_]]:
        """Return LK's start pixels (N, 2), which are predicted (N,) and which leave (N,)."""
        guess = self._pixels.copy()
        used = np.zeros(len(self._ids), bool)
        leaving = np.zeros(len(self._ids), bool)
        if predictions is None or not len(predictions.ids):
            return guess, used, leaving
        ids = np.asarray(predictions.ids, np.int64).reshape(-1)
        pixels = np.asarray(predictions.pixels, np.float64).reshape(-1, 2)
        if len(ids) != len(pixels):
            raise ValueError(f'predictions: {len(ids)} ids but {len(pixels)} pixels')
        finite = np.all(np.isfinite(pixels), axis=1)
        ids, pixels = ids[finite], pixels[finite]
        rows = np.searchsorted(self._ids, ids)  # self._ids is ascending
        known = rows < len(self._ids)
        known[known] = self._ids[rows[known]] == ids[known]
        rows, pixels = rows[known], pixels[known]
        height, width = shape
        inside = (
            (pixels[:, 0] >= 0)
            & (pixels[:, 0] <= width - 1)
            & (pixels[:, 1] >= 0)
            & (pixels[:, 1] <= height - 1)
        )
        guess[rows[inside]] = pixels[inside]
        used[rows[inside]] = True
        leaving[rows[~inside]] = True
        return guess, used, leaving

    def _follow(
        self,
        previous: GrayImage,
        gray: GrayImage,
        predictions: Predictions | None,
        drops: dict[str, int],
    ) -> int:
        """Track into ``gray``, dropping failures; return how many kept tracks were predicted."""
        config = self.config
        start = self._pixels
        guess, used, leaving = self._guesses(predictions, gray.shape)
        end, ok, error = self._lk(previous, gray, start, guess)
        keep = ok & np.all(np.isfinite(end), axis=1) & ~leaving
        drops['lost'] = int(np.count_nonzero(~keep & ~leaving))
        if config.max_lk_error > 0:
            bad = keep & ~(error <= config.max_lk_error)
            drops['error'] = int(np.count_nonzero(bad))
            keep &= ~bad
        height, width = gray.shape
        margin = config.border_margin_px
        outside = keep & (
            (end[:, 0] < margin)
            | (end[:, 0] > width - 1 - margin)
            | (end[:, 1] < margin)
            | (end[:, 1] > height - 1 - margin)
        )
        drops['border'] = int(np.count_nonzero(outside | leaving))
        keep &= ~outside
        if config.fb_threshold_px > 0 and np.any(keep):
            rows = np.flatnonzero(keep)
            # Back from the end, starting where the guess's offset says the start should be
            # (the start itself for tracks without a prediction).
            back_guess = end[rows] - (guess[rows] - start[rows])
            levels = self._levels_for(np.linalg.norm(guess[rows] - end[rows], axis=1))
            back, back_ok, _ = self._lk(gray, previous, end[rows], back_guess, levels)
            distance = np.linalg.norm(back - start[rows], axis=1)
            failed = ~(back_ok & (distance <= config.fb_threshold_px))
            drops['forward_backward'] = int(np.count_nonzero(failed))
            keep[rows[failed]] = False
        if config.max_drift_px > 0 and np.any(keep):
            rows = np.flatnonzero(keep)
            drifted = self._drifted(gray, rows, end[rows])
            drops['drift'] = int(np.count_nonzero(drifted))
            keep[rows[drifted]] = False
        self._pixels = np.ascontiguousarray(end, np.float32)
        self._ages = self._ages + 1
        self._keep(keep)
        predicted = int(np.count_nonzero(used[keep]))
        crowded = self._crowded()
        if np.any(crowded):
            predicted -= int(np.count_nonzero(used[keep][crowded]))
            drops['crowded'] = int(np.count_nonzero(crowded))
            self._keep(~crowded)
        return predicted

    def _levels_for(self, shifts: FloatArray) -> int:
        """Return the pyramid levels LK needs to cover ``shifts`` (M,) px."""
        reach = self.config.lk_window_px / 4.0
        largest = float(np.max(shifts, initial=0.0))
        levels = 0
        while levels < self.config.lk_pyramid_levels and largest > reach * 2**levels:
            levels += 1
        return levels

    def _keep(self, keep: NDArray[np.bool_]) -> None:
        """Keep the held tracks ``keep`` (N,); remember the others for re-identification."""
        if self.config.reid_min_ncc > 0 and self.config.max_dormant > 0:
            for row in np.flatnonzero(~keep):
                track_id = int(self._ids[row])
                self._dormant.pop(track_id, None)
                # a copy: a view would keep the whole stack of this image alive
                self._dormant[track_id] = (self._templates[row].copy(), int(self._ages[row]))
            self._forget(len(self._dormant) - self.config.max_dormant)
        self._ids, self._ages = self._ids[keep], self._ages[keep]
        self._pixels = np.ascontiguousarray(self._pixels[keep], np.float32)
        self._templates = self._templates[keep]
        self._returned.intersection_update(self._ids.tolist())

    def _forget(self, excess: int) -> None:
        """Forget ``excess`` remembered tracks, those not in SLAM's map first."""
        if excess <= 0:
            return
        unmapped = [i for i in self._dormant if i not in self._mapped][:excess]
        mapped = [i for i in self._dormant if i in self._mapped][: excess - len(unmapped)]
        for track_id in [*unmapped, *mapped]:
            del self._dormant[track_id]

    # --- re-identification ------------------------------------------------------------------

    def _revive(self, gray: GrayImage, predictions: Predictions | None) -> Search:
        """Bring back remembered tracks found where predicted; return the counts."""
        config = self.config
        if (
            predictions is None
            or predictions.covariances is None
            or not self._dormant
            or config.reid_min_ncc <= 0
        ):
            return Search()
        ids = np.asarray(predictions.ids, np.int64).reshape(-1)
        pixels = np.asarray(predictions.pixels, np.float64).reshape(-1, 2)
        covariances = np.asarray(predictions.covariances, np.float64).reshape(-1, 2, 2)
        if not len(ids) == len(pixels) == len(covariances):
            raise ValueError(
                f'predictions: {len(ids)} ids, {len(pixels)} pixels, {len(covariances)} '
                'covariances'
            )
        warps = np.zeros((len(ids), 2, 2)) if predictions.warps is None else predictions.warps
        if len(warps) != len(ids):
            raise ValueError(f'predictions: {len(ids)} ids, {len(warps)} warps')
        rows = {track_id: row for row, track_id in enumerate(self._ids.tolist())}
        templates = {i: t for i, (t, _) in self._dormant.items() if i not in rows}
        # the returned tracks show where the old map lies now (feature_reid's docstring)
        anchors = [k for k, i in enumerate(ids.tolist()) if i in self._returned]
        anchors = [k for k in anchors if np.all(np.isfinite(pixels[k]))]
        held = pixels[anchors], self._pixels[[rows[int(ids[k])] for k in anchors]].astype(float)
        pixels, covariances = aligned_predictions(
            pixels, covariances, ids, rows, self._pixels, config.reid_max_search_px
        )
        found, search = search_predicted(
            config, gray, templates, (ids, pixels, covariances, np.asarray(warps, float)), held
        )
        if not found:
            return search
        # all found come back; then the crowded rule, and max_features (``make_room``): a
        # revived track that loses goes back to sleep (not a drop); a held one it displaces
        # is 'crowded'
        back = [self._dormant.pop(track_id) for track_id, *_ in found]
        revived_ids = np.array([item[0] for item in found], np.int64)
        self._ids = np.concatenate([self._ids, revived_ids])
        self._ages = np.concatenate([self._ages, [age for _, age in back]])
        pixels = np.array([item[1:3] for item in found], np.float32)
        self._pixels = np.concatenate([self._pixels, pixels])
        self._templates = np.concatenate([self._templates, [template for template, _ in back]])
        order = np.argsort(self._ids, kind='stable')  # ids stay ascending
        self._ids, self._ages = self._ids[order], self._ages[order]
        self._pixels = np.ascontiguousarray(self._pixels[order], np.float32)
        self._templates = self._templates[order]
        is_revived = np.isin(self._ids, revived_ids)
        crowded = self._crowded()
        displaced = int(np.count_nonzero(crowded & ~is_revived))
        self._keep(~crowded)
        is_revived = is_revived[~crowded]
        excess = len(self._ids) - config.max_features
        if excess > 0:  # young unmapped tracks make room, else the weakest revived sleep
            score = {track_id: ncc for track_id, *_, ncc in found}
            scores = np.array([score.get(int(i), 0.0) for i in self._ids])
            out, pushed = make_room(self._ids, self._ages, is_revived, ids, scores, excess)
            displaced += pushed
            self._keep(~out)
            is_revived = is_revived[~out]
        self._returned.update(self._ids[is_revived].tolist())
        for row in np.flatnonzero(is_revived):  # the template as seen now
            u, v = (float(c) for c in self._pixels[row])
            self._templates[row] = cv2.getRectSubPix(gray, (self._side, self._side), (u, v))
        revived = int(np.count_nonzero(is_revived))
        return Search(
            revived, search.searched, search.unsearched, displaced, search.resolved,
            search.unaligned,
        )  # fmt: skip

    def _drifted(
        self, gray: GrayImage, rows: IntArray, pixels: NDArray[np.float32]
    ) -> NDArray[np.bool_]:
        """Return which tracks ``rows`` (M,), now at ``pixels`` (M, 2), left their templates."""
        side = self._side
        height, width = gray.shape
        per_row, per_column = width // side, height // side
        drifted = np.zeros(len(rows), bool)
        if per_row < 1 or per_column < 1:
            return drifted  # an image smaller than one template: no check
        capacity = per_row * per_column
        half = (side - 1) / 2.0
        for first in range(0, len(rows), capacity):
            chunk = slice(first, min(first + capacity, len(rows)))
            count = chunk.stop - chunk.start
            slots = np.arange(count)
            canvas = np.zeros((height, width), np.uint8)
            blocks = canvas[: per_column * side, : per_row * side].reshape(
                per_column, side, per_row, side
            )
            blocks[slots // per_row, :, slots % per_row, :] = self._templates[rows[chunk]]
            starts = np.column_stack(
                [(slots % per_row) * side + half, (slots // per_row) * side + half]
            ).astype(np.float32)
            end, ok, _ = self._lk(canvas, gray, starts, pixels[chunk], levels=0)  # small templates
            distance = np.linalg.norm(end - pixels[chunk], axis=1)
            drifted[chunk] = ~(ok & (distance <= self.config.max_drift_px))
        return drifted

    def _crowded(self) -> NDArray[np.bool_]:
        """Return which held tracks lie within half of min_distance_px of an older one."""
        return crowded_tracks(self._pixels, self._ids, self._ages, self.config.min_distance_px)

    # --- detection --------------------------------------------------------------------------

    def _detect(self, gray: GrayImage) -> int:
        """Start tracks where features are missing; return how many."""
        corners = self._detector.detect(gray, self._pixels)
        if not len(corners):
            return 0
        count = len(corners)
        templates = [cv2.getRectSubPix(gray, (self._side, self._side), (float(u), float(v)))
                     for u, v in corners]  # fmt: skip
        self._templates = np.concatenate(
            [self._templates, np.asarray(templates, np.uint8).reshape(-1, self._side, self._side)]
        )
        self._ids = np.concatenate([self._ids, np.arange(self._next_id, self._next_id + count)])
        self._pixels = np.ascontiguousarray(np.concatenate([self._pixels, corners]), np.float32)
        self._ages = np.concatenate([self._ages, np.ones(count, np.int64)])
        self._next_id += count
        return count

    def _clear(self) -> None:
        self._previous = None
        self._returned.clear()
        self._ids = np.zeros(0, np.int64)
        self._pixels = np.zeros((0, 2), np.float32)
        self._ages = np.zeros(0, np.int64)
        self._templates = np.zeros((0, self._side, self._side), np.uint8)
