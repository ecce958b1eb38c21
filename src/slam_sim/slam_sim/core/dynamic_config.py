"""Settings of the dynamic scene (``dynamic_scene``), validated on construction."""

from __future__ import annotations

import math
from dataclasses import dataclass

from slam_core.camera import CameraModel
from slam_sim.core.camera_path import LoopTurn

MOTION_KINDS = ('constant_velocity', 'turning', 'stop_and_go', 'model')
ROOM_SIZE_M = (10.0, 8.0, 3.0)
OBJECT_SPACE_M = ((4.8, 9.2), (1.2, 6.8), (0.5, 1.9))  # (min, max) per axis, object centres
MIN_DEPTH_M = 0.2
FOCAL_RANGE_PX = (150.0, 500.0)
_PRINCIPAL_POINT_PX = (320.7, 238.9)
_DISTORTION = (-0.05, 0.0, 0.0, 0.0, 0.0)  # plumb_bob (k1, k2, p1, p2, k3)


def _check(name: str, ok: bool, value: object, allowed: str) -> None:
    """Raise ValueError naming ``name`` unless ``ok``; ``allowed`` is an interval or a rule."""
    if not ok:
        verb = 'must be in' if allowed[:1] in '[(' else 'must be'
        raise ValueError(f'{name} = {value!r} {verb} {allowed}')


@dataclass(frozen=True)
class DynamicSceneConfig:
    """Run length, camera, noise, scene sizes and object motion parameters."""

    duration_s: float = 20.0
    rate_hz: float = 30.0
    focal_px: float = 300.0
    pixel_noise_px: float = 1.0
    static_points: int = 200
    objects: int = 4
    points_per_object: int = 6
    object_radius_m: float = 0.3
    motions: tuple[str, ...] = ('constant_velocity', 'turning', 'stop_and_go', 'constant_velocity')
    object_speed_m_s: tuple[float, float] = (0.3, 1.0)
    turn_rate_radps: tuple[float, float] = (0.3, 1.0)
    stop_duration_s: tuple[float, float] = (0.3, 0.8)
    go_duration_s: tuple[float, float] = (1.0, 3.0)
    hand_motion_m: float = 0.1
    velocity_prior_sigma_m_s: float = 0.5
    acceleration_psd: float = 0.05  # q, m^2/s^3
    max_range_m: float = 15.0
    image_margin_px: float = 2.0
    track_drop_probability: float = 0.0
    tracking_offset_px: float = 0.0
    tracking_offset_time_s: float = 1.0
    tracking_jump_probability: float = 0.0
    loop_away_s: float = 0.0  # 0: no loop; else the camera turns away this long and back
    loop_start_s: float = 4.0
    loop_turn_s: float = 1.5
    loop_angle_deg: float = 90.0
    keep_track_ids: bool = False  # a point back in view keeps its track id (known association)

    @property
    def tracking_correlation_time_s(self) -> float:
        """The tracking offsets' effective correlation time (jumps included), s."""
        jumps_per_s = -self.rate_hz * math.log1p(-self.tracking_jump_probability)
        return 1.0 / (1.0 / self.tracking_offset_time_s + jumps_per_s)

    def __post_init__(self) -> None:
        """Reject values the simulation cannot honour; the message names the field."""
        low, high = FOCAL_RANGE_PX
        _check('focal_px', low <= self.focal_px <= high, self.focal_px, f'[{low:g}, {high:g}] px')
        _check('duration_s', 0.0 < self.duration_s <= 3600.0, self.duration_s, '(0, 3600] s')
        _check('rate_hz', 0.0 < self.rate_hz <= 1000.0, self.rate_hz, '(0, 1000] Hz')
        _check('duration_s', self.frame_count >= 3, self.duration_s, '>= 3 frames long')
        _check('pixel_noise_px', 0.0 <= self.pixel_noise_px <= 50.0, self.pixel_noise_px,
               '[0, 50] px')  # fmt: skip
        for name, least in (('static_points', 0), ('objects', 0), ('points_per_object', 1)):
            value = getattr(self, name)
            _check(name, isinstance(value, int) and value >= least, value, f'an int >= {least}')
        _check('object_radius_m', 0.0 <= self.object_radius_m <= 1.0, self.object_radius_m,
               '[0, 1] m')  # fmt: skip
        _check('motions', len(self.motions) > 0, self.motions, 'at least one motion kind')
        for kind in self.motions:
            _check('motions', kind in MOTION_KINDS, kind, f'one of {", ".join(MOTION_KINDS)}')
        for name in ('object_speed_m_s', 'turn_rate_radps', 'stop_duration_s', 'go_duration_s'):
            pair = getattr(self, name)
            _check(
                name, len(pair) == 2 and 0.0 < pair[0] <= pair[1], pair, 'a pair 0 < min <= max'
            )
        _check('hand_motion_m', 0.0 <= self.hand_motion_m <= 0.5, self.hand_motion_m,
               '[0, 0.5] m')  # fmt: skip
        for name in ('velocity_prior_sigma_m_s', 'acceleration_psd'):
            _check(name, getattr(self, name) >= 0.0, getattr(self, name), '>= 0')
        _check('max_range_m', self.max_range_m > MIN_DEPTH_M, self.max_range_m, '> 0.2 m')
        _check('image_margin_px', 0.0 <= self.image_margin_px <= 100.0, self.image_margin_px,
               '[0, 100] px')  # fmt: skip
        drop = self.track_drop_probability
        _check('track_drop_probability', 0.0 <= drop < 1.0, drop, '[0, 1)')
        offset, time_s = self.tracking_offset_px, self.tracking_offset_time_s
        _check('tracking_offset_px', 0.0 <= offset <= 50.0, offset, '[0, 50] px')
        _check('tracking_offset_time_s', time_s > 0.0, time_s, '> 0 s')
        jump = self.tracking_jump_probability
        _check('tracking_jump_probability', 0.0 <= jump < 1.0, jump, '[0, 1)')
        _check('loop_away_s', self.loop_away_s >= 0.0, self.loop_away_s, '>= 0 s')
        _check('loop_start_s', self.loop_start_s >= 0.0, self.loop_start_s, '>= 0 s')
        _check('loop_turn_s', self.loop_turn_s > 0.0, self.loop_turn_s, '> 0 s')
        _check('keep_track_ids', isinstance(self.keep_track_ids, bool), self.keep_track_ids,
               'a bool')  # fmt: skip
        angle = self.loop_angle_deg
        _check('loop_angle_deg', -180.0 <= angle <= 180.0, angle, '[-180, 180] deg')
        if self.loop_away_s > 0.0:
            back = self.loop_start_s + 2.0 * self.loop_turn_s + self.loop_away_s
            _check('loop_away_s', back < self.duration_s, self.loop_away_s,
                   f'short enough to turn back before the run ends ({back:g} s >= '
                   f'duration_s {self.duration_s:g} s)')  # fmt: skip

    @property
    def loop(self) -> LoopTurn | None:
        """The camera's turn away and back (``camera_path.LoopTurn``), None without a loop."""
        if self.loop_away_s <= 0.0:
            return None
        return LoopTurn(
            self.loop_start_s,
            self.loop_turn_s,
            self.loop_away_s,
            math.radians(self.loop_angle_deg),
        )

    @property
    def frame_count(self) -> int:
        """Number of frames K, at run times k / rate_hz s, k = 0 .. K-1."""
        return round(self.duration_s * self.rate_hz)

    def camera(self) -> CameraModel:
        """Return the 640 x 480 camera: fx = fy = focal_px, k1 = -0.05."""
        return CameraModel.from_intrinsics(
            640, 480, (self.focal_px, self.focal_px), _PRINCIPAL_POINT_PX, _DISTORTION
        )
