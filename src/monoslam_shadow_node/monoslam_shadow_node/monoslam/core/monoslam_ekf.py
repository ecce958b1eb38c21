"""The MonoSLAM EKF steps: prediction, search regions, gated and consider updates (Joseph form).

Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from monoslam_shadow_node.monoslam.core.monoslam_init import MIN_KNOWN_POINTS
from monoslam_shadow_node.monoslam.core.monoslam_model import (
    CAMERA_SIZE,
    INVERSE_DEPTH_SIZE,
    Q_SLICE,
    R_SLICE,
    predict_camera,
    project_features,
)
from monoslam_shadow_node.monoslam.core.monoslam_state import FeatureBlock, FilterState
from monoslam_shadow_node.monoslam.core.monoslam_types import MonoSlamConfig, UpdateCounts
from slam_core.arrays import FloatArray, IntArray
from slam_core.camera import CameraModel


def predict(state: FilterState, dt_s: float, config: MonoSlamConfig) -> None:
    """Constant velocity prediction over ``dt_s`` s; tracker offset states decay towards 0."""
    sigmas = config.linear_acceleration_sigma, config.angular_acceleration_sigma
    camera, f, q = predict_camera(state.x[:CAMERA_SIZE], dt_s, *sigmas)
    state.x[:CAMERA_SIZE] = camera
    c = slice(0, CAMERA_SIZE)
    history = state.carried_history()  # F applies to the remembered poses' too (pose_cross)
    if history is not None:
        history[c] = f @ history[c]
    state.p[c, c] = f @ state.p[c, c] @ f.T + q
    state.p[c, CAMERA_SIZE:] = f @ state.p[c, CAMERA_SIZE:]
    state.p[CAMERA_SIZE:, c] = state.p[c, CAMERA_SIZE:].T
    offsets = offset_indices(state)
    if len(offsets):
        decay, fresh = config.tracking_noise.step(dt_s)
        state.x[offsets] *= decay
        if history is not None:
            history[offsets] *= decay
        state.p[offsets, :] *= decay
        state.p[:, offsets] *= decay
        state.p[offsets, offsets] += fresh


def offset_indices(state: FilterState) -> IntArray:
    """Return the indices in x (K,) of every feature's tracker offset (none without them)."""
    spans = [feature.offset for feature in state.features if feature.offset is not None]
    if not spans:
        return np.zeros(0, dtype=np.int64)
    return np.concatenate([np.arange(span.start, span.stop) for span in spans])


def feature_jacobian(feature: FeatureBlock, d_point: FloatArray) -> FloatArray:
    """Return d(pixel)/d(feature's states) (2, extent): the point's, then I for its offset."""
    if not feature.offset_size:
        return d_point
    return np.hstack([d_point, np.eye(2)])


def predicted_measurements(
    state: FilterState,
    camera_model: CameraModel,
    dt_s: float,
    config: MonoSlamConfig,
    ids: list[int] | None = None,
    *,
    covariances: bool = True,
) -> tuple[IntArray, FloatArray, FloatArray, FloatArray]:
    """Return ids (M,), pixels (M, 2) and innovation covariances (M, 2, 2) px^2 (zeros without
    ``covariances``) ``dt_s`` s ahead, and the predicted camera (13,); state unchanged."""
    sigmas = config.linear_acceleration_sigma, config.angular_acceleration_sigma
    camera, f, q = predict_camera(state.x[:CAMERA_SIZE], dt_s, *sigmas)
    wanted = None if ids is None else set(ids)
    features = [feature for feature in state.features if wanted is None or feature.id in wanted]
    points = [
        (state.x[feature.start : feature.start + feature.size], feature.reference)
        for feature in features
    ]
    pixels, d_camera, d_feature, depth = project_features(
        camera_model, camera, points, jacobians=covariances
    )
    front = np.flatnonzero(depth > 0.0)
    decay, offset_noise = config.tracking_noise.step(dt_s)
    out_ids = np.array([features[k].id for k in front.tolist()], dtype=np.int64)
    out_pixels = pixels[front].reshape(-1, 2)
    offsets = [k for k, row in enumerate(front.tolist()) if features[row].offset is not None]
    if offsets:  # the offset decays over dt_s
        index = np.array([features[front[k]].start + features[front[k]].size for k in offsets])
        out_pixels[offsets] = out_pixels[offsets] + decay * state.x[index[:, None] + [0, 1]]
    out_s = np.zeros((len(front), 2, 2))
    if not covariances or not len(front):
        return out_ids, out_pixels, out_s, camera
    p_cc = f @ state.p[:CAMERA_SIZE, :CAMERA_SIZE] @ f.T + q
    h_c_all = d_camera[front]
    groups: dict[tuple[int, int], list[int]] = {}
    for k, row in enumerate(front.tolist()):
        groups.setdefault((features[row].size, features[row].offset_size), []).append(k)
    for (size, offset_size), members in groups.items():
        rows = front[members]
        group = [features[row] for row in rows.tolist()]
        extent = size + offset_size
        h_f = np.zeros((len(members), 2, extent))
        h_f[:, :, :size] = np.array([d_feature[row] for row in rows.tolist()])
        fresh = 0.0
        if offset_size:
            h_f[:, :, size:] = decay * np.eye(2)
            fresh = offset_noise
        index = np.array([feature.start for feature in group])[:, None] + np.arange(extent)
        p_cf = f @ np.swapaxes(state.p[:CAMERA_SIZE][:, index], 0, 1)
        h_c = h_c_all[members]
        h_f_t = np.swapaxes(h_f, 1, 2)
        cross = h_c @ p_cf @ h_f_t
        own = h_f @ state.p[index[:, :, None], index[:, None, :]] @ h_f_t
        s = h_c @ p_cc @ np.swapaxes(h_c, 1, 2) + cross + np.swapaxes(cross, 1, 2) + own
        s += (fresh + measurement_variance_of(group[0], config)) * np.eye(2)
        out_s[members] = s
    return out_ids, out_pixels, out_s, camera


@dataclass(frozen=True, eq=False)
class Match:
    """A measurement: raw pixel (2,) of a known world point (3,) m or of a state feature."""

    pixel: FloatArray
    point: FloatArray | None = None
    feature: FeatureBlock | None = None


@dataclass(frozen=True, eq=False)
class Linearized:
    """A match's prediction: pixel (2,), H_c (2, 13), H_f (2, k), the feature's block (or None)."""

    predicted: FloatArray
    h_c: FloatArray
    h_f: FloatArray
    block: slice | None
    second_order: FloatArray = field(default_factory=lambda: np.zeros((2, 2)))

    def innovation_covariance(self, p: FloatArray, sigma2: float) -> FloatArray:
        """Return S = H P H^T + sigma2 I + the second-order term (2, 2) px^2."""
        c = slice(0, CAMERA_SIZE)
        s = self.h_c @ p[c, c] @ self.h_c.T + sigma2 * np.eye(2) + self.second_order
        if self.block is not None:
            cross = self.h_c @ p[c, self.block] @ self.h_f.T
            s += cross + cross.T + self.h_f @ p[self.block, self.block] @ self.h_f.T
        return s

    def row(self, n: int) -> FloatArray:
        """Return H (2, n) over the whole state of length ``n``."""
        h = np.zeros((2, n))
        h[:, :CAMERA_SIZE] = self.h_c
        if self.block is not None:
            h[:, self.block] = self.h_f
        return h

    def p_h_t(self, p: FloatArray) -> FloatArray:
        """Return P H^T (n, 2) without forming H."""
        out = p[:, :CAMERA_SIZE] @ self.h_c.T
        if self.block is not None:
            out += p[:, self.block] @ self.h_f.T
        return np.asarray(out, dtype=np.float64)


@dataclass(frozen=True, eq=False)
class UpdateOutcome:
    """What an update did: measured and rejected feature ids, known points used, counts."""

    measured: list[int]
    rejected: list[int]
    known_used: int
    counts: UpdateCounts


def matches(
    state: FilterState,
    observed: dict[int, FloatArray],
    known: list[tuple[FloatArray, FloatArray]],
) -> list[Match]:
    """Return the known points' matches, then the observed state features', in state order."""
    out = [Match(pixel, point=point) for point, pixel in known]
    return out + [Match(observed[f.id], feature=f) for f in state.features if f.id in observed]


def linearize_all(
    state: FilterState,
    camera_model: CameraModel,
    all_matches: list[Match],
    second_order: bool = False,
) -> list[Linearized | None]:
    """Return every match's prediction at the current state (None behind the camera)."""
    if not all_matches:
        return []
    camera = state.x[:CAMERA_SIZE]
    points: list[tuple[FloatArray, FloatArray | None]] = []
    blocks: list[slice | None] = []
    for match in all_matches:
        if match.point is not None:
            points.append((match.point, None))
            blocks.append(None)
        elif (feature := match.feature) is not None:
            points.append(
                (state.x[feature.start : feature.start + feature.size], feature.reference)
            )
            blocks.append(slice(feature.start, feature.start + feature.extent))
        else:
            raise ValueError('a match needs a known point or a feature')
    pixels, d_camera, d_feature, depth = project_features(camera_model, camera, points)
    out: list[Linearized | None] = []
    for k, match in enumerate(all_matches):
        if not depth[k] > 0.0:
            out.append(None)
        elif (feature := match.feature) is None:
            out.append(Linearized(pixels[k], d_camera[k], d_feature[k], None))
        else:  # the offset, if a state, adds to the projection
            offset = feature.offset
            pixel = pixels[k] if offset is None else pixels[k] + state.x[offset]
            h_f = feature_jacobian(feature, d_feature[k])
            extra = np.zeros((2, 2))
            if second_order:
                extra = second_order_covariance(state, feature, d_feature[k])
            out.append(Linearized(pixel, d_camera[k], h_f, blocks[k], extra))
    return out


def second_order_covariance(
    state: FilterState, feature: FeatureBlock, d_point: FloatArray
) -> FloatArray:
    """Return an inverse-depth feature's second-order measurement covariance (2, 2) px^2."""
    if feature.size != INVERSE_DEPTH_SIZE or state.x[feature.start + 5] <= 1e-9:
        return np.zeros((2, 2))
    start = feature.start
    rho = float(state.x[start + 5])
    anchor = np.arange(start, start + 3)
    centre = np.arange(R_SLICE.start, R_SLICE.stop)
    both = np.concatenate([anchor, centre, [start + 5]])
    p = state.p[np.ix_(both, both)]
    sigma_d = p[:3, :3] - p[:3, 3:6] - p[3:6, :3] + p[3:6, 3:6]
    c = p[:3, 6] - p[3:6, 6]
    g = d_point[:, :3] / rho
    return np.asarray(g @ (p[6, 6] * sigma_d + np.outer(c, c)) @ g.T, dtype=np.float64)


def gate_all(
    all_matches: list[Match],
    linearized: list[Linearized | None],
    p: FloatArray,
    config: MonoSlamConfig,
) -> list[bool]:
    """Return per match whether it is in front and inside the chi-square gate of S from ``p``."""
    rows = [k for k, lin in enumerate(linearized) if lin is not None]
    used = [lin for lin in linearized if lin is not None]
    passed = [False] * len(all_matches)
    if not used:
        return passed
    c = slice(0, CAMERA_SIZE)
    h_c = np.array([lin.h_c for lin in used])
    variances = np.array([measurement_variance(all_matches[k], config) for k in rows])
    s = h_c @ p[c, c] @ np.swapaxes(h_c, 1, 2) + variances[:, None, None] * np.eye(2)
    blocks = [(i, lin.block, lin.h_f) for i, lin in enumerate(used) if lin.block is not None]
    for size in {h_f.shape[1] for _, _, h_f in blocks}:
        group = [(i, block, h_f) for i, block, h_f in blocks if h_f.shape[1] == size]
        members = [i for i, _, _ in group]
        index = np.array([block.start for _, block, _ in group])[:, None] + np.arange(size)
        h_f = np.array([h_f for _, _, h_f in group])
        h_f_t = np.swapaxes(h_f, 1, 2)
        cross = h_c[members] @ np.swapaxes(p[c][:, index], 0, 1) @ h_f_t
        own = h_f @ p[index[:, :, None], index[:, None, :]] @ h_f_t
        s[members] += cross + np.swapaxes(cross, 1, 2) + own
    innovation = np.array(
        [all_matches[k].pixel - lin.predicted for k, lin in zip(rows, used, strict=True)]
    )
    s += np.array([lin.second_order for lin in used])
    whitened = np.linalg.solve(s, innovation[:, :, None])[:, :, 0]
    for k, value in zip(rows, np.einsum('ni,ni->n', innovation, whitened), strict=True):
        passed[k] = bool(value <= config.gate)
    return passed


MIN_POSE_POINTS = 3
"""Points that fix a camera pose (P3P)."""
MIN_TRUSTED_POINTS = MIN_POSE_POINTS + 2
"""Trusted measurements a frame needs for its update to find a wrong one among them: any
three fix a pose, a fourth shows that one of them is wrong, a fifth says which. With fewer,
the cleared features on probation join the update (``split_probation``), unless at least
``MIN_KNOWN_POINTS`` known points are among them: those are certain (a target's geometry,
found by its code), and fix the camera on their own."""


def split_probation(all_matches: list[Match]) -> tuple[list[Match], list[Match]]:
    """Return the matches that update the camera and those of features on probation."""
    on_probation = [m for m in all_matches if m.feature is not None and m.feature.probation]
    rest = [m for m in all_matches if m.feature is None or not m.feature.probation]
    known = sum(1 for m in rest if m.feature is None)
    if on_probation and len(rest) < MIN_TRUSTED_POINTS and known < MIN_KNOWN_POINTS:
        for match in on_probation:
            assert match.feature is not None
            match.feature.probation = not match.feature.cleared
        rest = [m for m in all_matches if m.feature is None or not m.feature.probation]
        on_probation = [m for m in on_probation if m.feature is not None and m.feature.probation]
    return rest, on_probation


def probation_update(
    state: FilterState,
    camera_model: CameraModel,
    on_probation: list[Match],
    config: MonoSlamConfig,
) -> set[int]:
    """Consider-update each feature on probation inside the gate; return the indices used."""
    linearized = linearize_all(state, camera_model, on_probation, config.second_order)
    gates = gate_all(on_probation, linearized, state.p, config)
    used: set[int] = set()
    for index, (match, lin) in enumerate(zip(on_probation, linearized, strict=True)):
        if lin is not None and gates[index]:
            consider_update(state, match, lin, measurement_variance(match, config))
            used.add(index)
    return used


def consider_update(
    state: FilterState, match: Match, linearized: Linearized, sigma2: float
) -> None:
    """Schmidt ('consider') update of one feature: only its own block moves."""
    block = linearized.block
    if block is None:
        raise ValueError('a consider update needs a feature of the state')
    b = linearized.p_h_t(state.p)
    s = linearized.innovation_covariance(state.p, sigma2)
    gain = np.linalg.solve(s, b[block].T).T
    state.x[block] = state.x[block] + gain @ (match.pixel - linearized.predicted)
    history = state.carried_history()
    if history is not None:
        history[block] -= gain @ linearized.p_h_t(history.T).T
    k_b = gain @ b.T
    rows = state.p[block, :] - k_b
    own = rows[:, block] - k_b[:, block].T + gain @ s @ gain.T
    rows[:, block] = 0.5 * (own + own.T)
    state.p[block, :] = rows
    state.p[:, block] = rows.T


def measurement_variance(match: Match, config: MonoSlamConfig) -> float:
    """Return a match's R per coordinate, px^2: known point or ``measurement_variance_of``."""
    if match.feature is None:
        return config.pixel_sigma_px**2
    return measurement_variance_of(match.feature, config)


def measurement_variance_of(feature: FeatureBlock, config: MonoSlamConfig) -> float:
    """Return a tracked feature's R per coordinate, px^2 (white alone if its offset is a state)."""
    if feature.offset_size:
        return config.pixel_sigma_px**2
    return config.feature_sigma_px**2


def marginal_variance(match: Match, config: MonoSlamConfig) -> float:
    """Return a match's pixel variance about its point's projection, px^2 (offset included)."""
    sigma = config.pixel_sigma_px if match.feature is None else config.feature_sigma_px
    return sigma * sigma


def apply_update(
    state: FilterState, used: list[tuple[Match, Linearized]], config: MonoSlamConfig
) -> None:
    """Update with all ``used`` measurements at once (Joseph form; nothing when empty)."""
    if used:
        joseph_update(state, *stacked(used, config))


def stacked(
    used: list[tuple[Match, Linearized]], config: MonoSlamConfig
) -> tuple[FloatArray, FloatArray, FloatArray, IntArray, FloatArray]:
    """Return H (2m, k), residual (2m,), R diagonal (2m,), columns (k,), blocks (m, 2, 2)."""
    blocks = sorted(
        {(lin.block.start, lin.block.stop) for _, lin in used if lin.block is not None}
    )
    columns = np.concatenate(
        [np.arange(CAMERA_SIZE)] + [np.arange(start, stop) for start, stop in blocks]
    )
    where = {start: CAMERA_SIZE + sum(b - a for a, b in blocks[:k])
             for k, (start, _) in enumerate(blocks)}  # fmt: skip
    h = np.zeros((2 * len(used), len(columns)))
    for k, (_, linearized) in enumerate(used):
        h[2 * k : 2 * k + 2, :CAMERA_SIZE] = linearized.h_c
        if (block := linearized.block) is not None:
            first = where[block.start]
            h[2 * k : 2 * k + 2, first : first + block.stop - block.start] = linearized.h_f
    residual = np.concatenate([match.pixel - linearized.predicted for match, linearized in used])
    variances = np.repeat([measurement_variance(match, config) for match, _ in used], 2)
    second_order = np.array([linearized.second_order for _, linearized in used])
    return h, residual, variances, columns, second_order


def record_attempts(all_matches: list[Match], accepted: set[int]) -> UpdateOutcome:
    """Count each feature's attempt; return measured, rejected ids and known points used."""
    measured: list[int] = []
    rejected: list[int] = []
    known_used = 0
    for index, match in enumerate(all_matches):
        ok = index in accepted
        feature = match.feature
        if feature is None:
            known_used += int(ok)
            continue
        feature.attempts += 1
        (measured if ok else rejected).append(feature.id)
        feature.successes += int(ok)
        feature.consecutive_failures = 0 if ok else feature.consecutive_failures + 1
    counts = UpdateCounts(rejected=len(all_matches) - len(accepted))
    return UpdateOutcome(measured, rejected, known_used, counts)


def gated_update(
    state: FilterState,
    camera_model: CameraModel,
    observed: dict[int, FloatArray],
    known: list[tuple[FloatArray, FloatArray]],
    config: MonoSlamConfig,
) -> UpdateOutcome:
    """Gate and apply all measurements, then those on probation; return what was measured."""
    all_matches, on_probation = split_probation(matches(state, observed, known))
    used: list[tuple[Match, Linearized]] = []
    accepted: set[int] = set()
    linearized_all = linearize_all(state, camera_model, all_matches, config.second_order)
    gates = gate_all(all_matches, linearized_all, state.p, config)
    for index, (match, linearized) in enumerate(zip(all_matches, linearized_all, strict=True)):
        if linearized is not None and gates[index]:
            used.append((match, linearized))
            accepted.add(index)
    apply_update(state, used, config)
    considered = probation_update(state, camera_model, on_probation, config)
    accepted |= {len(all_matches) + index for index in considered}
    outcome = record_attempts(all_matches + on_probation, accepted)
    counts = UpdateCounts(
        compatible=len(used), rejected=outcome.counts.rejected, probation=len(considered)
    )
    return UpdateOutcome(outcome.measured, outcome.rejected, outcome.known_used, counts)


def joseph_update(
    state: FilterState,
    h: FloatArray,
    residual: FloatArray,
    variances: FloatArray,
    columns: IntArray | None = None,
    second_order: FloatArray | None = None,
) -> None:
    """x += K nu, P in Joseph form, R = diag(``variances``) + ``second_order``; renormalize q.

    ``h`` (m, k) holds H's ``columns`` (k,) of the state (None: all); H is zero elsewhere."""
    if columns is None:
        columns = np.arange(len(state.x))
    ph_t = state.p[:, columns] @ h.T
    s = innovation_matrix(h, ph_t[columns], variances, second_order)
    gain = ph_t @ np.linalg.inv(s)  # S is m x m, well conditioned (R >= pixel noise)
    state.x = state.x + gain @ residual
    half = gain @ (0.5 * (s @ gain.T) - ph_t.T)
    p = half + half.T  # (not in place: numpy would copy the transposed operand first)
    p += state.p
    jacobian = renormalize_quaternion(state.x)
    history = state.carried_history()
    if history is not None:
        history = history - gain @ (h @ history[columns])
        history[Q_SLICE] = jacobian @ history[Q_SLICE]
        state.history = history
    rows = jacobian @ p[Q_SLICE, :]
    corner = rows[:, Q_SLICE] @ jacobian.T
    p[Q_SLICE, :] = rows
    p[:, Q_SLICE] = rows.T
    p[Q_SLICE, Q_SLICE] = 0.5 * (corner + corner.T)
    state.p = p


def innovation_matrix(
    h: FloatArray, h_p: FloatArray, variances: FloatArray, second_order: FloatArray | None
) -> FloatArray:
    """Return S = H P H^T + R (m, m) from H (m, k) and ``h_p`` = P H^T over H's columns (k, m)."""
    s = h @ h_p + np.diag(variances)
    for k, block in enumerate(() if second_order is None else second_order):
        s[2 * k : 2 * k + 2, 2 * k : 2 * k + 2] += block
    return np.asarray(s, dtype=np.float64)


def renormalize_quaternion(x: FloatArray) -> FloatArray:
    """Make the camera quaternion in ``x`` (n,) unit, in place; return its Jacobian (4, 4)."""
    norm = float(np.linalg.norm(x[Q_SLICE]))
    q = x[Q_SLICE] / norm
    x[Q_SLICE] = q
    return np.asarray((np.eye(4) - np.outer(q, q)) / norm, dtype=np.float64)


def pose_cross(state: FilterState) -> tuple[list[int], FloatArray]:
    """Return the remembered poses' stamps and Cov(e_now, e_then) (K, 6, 6)."""
    history = state.carried_history()
    if history is None or not state.history_stamps:
        return [], np.zeros((0, 6, 6))
    now = state.pose_jacobian() @ history[:CAMERA_SIZE]  # (6, 6 K)
    crosses = now.reshape(6, -1, 6).transpose(1, 0, 2)
    return list(state.history_stamps), np.asarray(crosses, dtype=np.float64)
