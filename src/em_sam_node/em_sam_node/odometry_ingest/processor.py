"""odometry_ingest's processor: wheel odometry in, keyframe-to-keyframe increments (eq. 2)
out; see docs/design/em_sam_core.md."""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from em_sam_node.core.inputs import Increment
from slam_core.arrays import FloatArray
from slam_core.geometry.se2 import increment_between, wrap_angle
from slam_core.params import NON_NEGATIVE, POSITIVE, check_fields, ruled


@dataclass(frozen=True)
class IngestConfig:
    """Validated odometry_ingest settings (SI units)."""

    keyframe_distance_m: float = ruled(0.5, range=POSITIVE)
    keyframe_angle_rad: float = ruled(0.35, range=POSITIVE)
    keyframe_interval_s: float = ruled(5.0, range=POSITIVE)
    observation_delay_s: float = ruled(0.5, range=NON_NEGATIVE)
    observation_silence_s: float = ruled(5.0, range=POSITIVE)
    noise_alphas: tuple[float, float, float, float] = ruled(
        (0.05, 0.001, 0.01, 0.001), range=NON_NEGATIVE, length=4
    )
    min_sigma_xy_m: float = ruled(0.002, range=POSITIVE)
    min_sigma_theta_rad: float = ruled(0.002, range=POSITIVE)
    reset_jump_m: float = ruled(1.0, range=POSITIVE)
    reset_backwards_s: float = ruled(1.0, range=POSITIVE)
    reset_speed_mps: float = ruled(5.0, range=POSITIVE)
    reset_sigma: tuple[float, float, float] = ruled((1.0, 1.0, 0.5), range=POSITIVE, length=3)
    max_buffer_s: float = ruled(30.0, range=POSITIVE)
    startup_hold_s: float = ruled(5.0, range=NON_NEGATIVE)

    def __post_init__(self) -> None:
        check_fields(self, prefix='parameter ')
        if self.startup_hold_s >= self.max_buffer_s:
            raise ValueError(
                f'parameter startup_hold_s={self.startup_hold_s!r}: must be less than '
                f'max_buffer_s={self.max_buffer_s!r}, or held keyframes lose their odometry'
            )
        if self.observation_delay_s >= self.max_buffer_s:
            raise ValueError(
                f'parameter observation_delay_s={self.observation_delay_s!r}: must be less than '
                f'max_buffer_s={self.max_buffer_s!r}, or held-back keyframes lose their odometry'
            )


def motion_covariance(config: IngestConfig, u: FloatArray) -> FloatArray:
    """Return the (3,3) covariance of increment ``u`` under the odometry noise model."""
    a1, a2, a3, a4 = config.noise_alphas
    distance2 = float(u[0] ** 2 + u[1] ** 2)
    turn2 = float(u[2] ** 2)
    var_xy = a3 * distance2 + a4 * turn2 + config.min_sigma_xy_m**2
    var_theta = a1 * turn2 + a2 * distance2 + config.min_sigma_theta_rad**2
    return np.diag([var_xy, var_xy, var_theta])


def interpolate_pose(
    stamp_ns: int, before: tuple[int, FloatArray], after: tuple[int, FloatArray]
) -> FloatArray:
    """Return the pose (3,) at ``stamp_ns`` between two stamped poses (linear, shortest turn)."""
    (t0, p0), (t1, p1) = before, after
    if t1 == t0:
        return p0.copy()
    alpha = (stamp_ns - t0) / (t1 - t0)
    pose = p0 + alpha * (p1 - p0)
    pose[2] = wrap_angle(np.array([p0[2] + alpha * wrap_angle(np.array([p1[2] - p0[2]]))[0]]))[0]
    return pose


@dataclass
class _State:
    samples: list[tuple[int, FloatArray]] = field(default_factory=list)  # (stamp, pose)
    pending_stamps: list[int] = field(default_factory=list)  # observation stamps, sorted
    keyframe: tuple[int, FloatArray] | None = None  # last emitted keyframe
    reset_pending: bool = False
    rewound_until_ns: int | None = None  # dropping samples up to this stamp
    rewound_dropped: int = 0
    # Samples up to this stamp were found not to have moved enough from the current keyframe.
    checked_ns: int | None = None
    hold_ended: str = ''  # how the startup hold ended; '' while it holds
    first_ns: int | None = None  # the first odometry stamp
    # The observation stream's progress: its newest stamp, and the newest odometry stamp when
    # that message came (how long ago, in odometry time, the stream last spoke).
    progress_ns: int | None = None
    progress_at_ns: int | None = None


class OdometryIngest:
    """Turns odometry samples and observation stamps into keyframe increments."""

    def __init__(self, config: IngestConfig, warn: Callable[[str], None] | None = None) -> None:
        self.config = config
        self.warn = warn if warn is not None else (lambda _message: None)
        self._state = _State()
        self.dropped_samples = 0
        self.resets = 0
        self.refused_stamps = 0  # observation stamps refused a keyframe (warned)

    @property
    def hold_ended(self) -> str:
        """How the startup hold ended, '' while it holds (the node logs it once)."""
        return self._state.hold_ended

    # -- input ----------------------------------------------------------------------------
    def add_odometry(self, stamp_ns: int, pose: FloatArray) -> list[Increment]:
        """Add one odometry pose (x m, y m, theta rad) in the odom frame; return new increments."""
        state = self._state
        if not np.all(np.isfinite(pose)):
            self.dropped_samples += 1
            self.warn(
                f'odometry at stamp {stamp_ns} ns has a non-finite pose {pose.tolist()}; dropped'
            )
            return []
        pose = np.array([pose[0], pose[1], wrap_angle(np.array([pose[2]]))[0]], dtype=float)
        if state.rewound_until_ns is not None:
            return self._after_rewind(stamp_ns, pose)
        if state.samples:
            last_stamp, last_pose = state.samples[-1]
            backwards_s = (last_stamp - stamp_ns) / 1e9
            jump_m = float(np.hypot(*(pose[:2] - last_pose[:2])))
            speed_mps = jump_m / max(-backwards_s, 1e-9)
            teleported = (
                jump_m > self.config.reset_jump_m and speed_mps > self.config.reset_speed_mps
            )
            if backwards_s > self.config.reset_backwards_s:
                return self._rewind(stamp_ns, backwards_s)
            if stamp_ns <= last_stamp:
                self.dropped_samples += 1
                self.warn(
                    f'odometry stamp {stamp_ns} ns is not after the previous one '
                    f'({last_stamp} ns); out-of-order sample dropped'
                )
                return []
            if teleported:
                return self._reset(stamp_ns, pose, jump_m)
        state.samples.append((stamp_ns, pose))
        if state.keyframe is None:
            state.keyframe = (stamp_ns, pose.copy())  # the first keyframe: the first sample
            state.first_ns = stamp_ns
            self._release_before_odometry(stamp_ns)
        if not state.hold_ended:
            held_s = (stamp_ns - state.samples[0][0]) / 1e9
            if held_s < self.config.startup_hold_s:
                return []
            state.hold_ended = f'after {held_s:.1f} s of odometry without a timely observation'
        return self._emit(horizon_ns=self._horizon())

    def add_observation_stamp(self, stamp_ns: int, *, seen: bool = True) -> list[Increment]:
        """Ask for a keyframe at an observation stamp; return increments that became ready.

        ``seen=False``: the source handled this stamp and saw nothing (an empty array). It
        makes no keyframe; it says how far the source has got, so that keyframes wait for a
        source that lags but keeps publishing (docs/design/em_sam_nodes.md).
        """
        state = self._state
        if state.progress_ns is None or stamp_ns > state.progress_ns:
            state.progress_ns = stamp_ns
        state.progress_at_ns = state.samples[-1][0] if state.samples else None
        if not seen:
            return self._release(stamp_ns) if state.samples else []
        if state.first_ns is not None and stamp_ns < state.first_ns:
            self.refused_stamps += 1
            self.warn(
                f'observation stamp {stamp_ns} ns came before the first odometry (at '
                f'{state.first_ns} ns); it gets no keyframe'
            )
            return []
        if state.keyframe is not None and stamp_ns <= state.keyframe[0]:
            if stamp_ns != state.keyframe[0]:
                self.refused_stamps += 1
                self.warn(
                    f'observation stamp {stamp_ns} ns is older than the last keyframe '
                    f'({state.keyframe[0]} ns): its source was silent for '
                    'observation_silence_s, or lagged by more than max_buffer_s, or publishes '
                    'only what it sees (no empty arrays) and lagged by more than '
                    'observation_delay_s'
                )
            return []
        if state.rewound_until_ns is not None:
            self.refused_stamps += 1
            self.warn(
                f'observation at stamp {stamp_ns} ns came while the odometry clock is rewound '
                f'(see the earlier warning); it gets no keyframe'
            )
            return []
        if not state.samples:
            self._hold_before_odometry(stamp_ns)
            return []
        if stamp_ns < state.samples[0][0]:
            self.refused_stamps += 1
            self.warn(
                f'observation stamp {stamp_ns} ns is older than the buffered odometry (from '
                f'{state.samples[0][0]} ns); it gets no keyframe (raise max_buffer_s to keep it)'
            )
            return []
        index = bisect.bisect_left(state.pending_stamps, stamp_ns)
        if index == len(state.pending_stamps) or state.pending_stamps[index] != stamp_ns:
            state.pending_stamps.insert(index, stamp_ns)
        return self._release(stamp_ns)

    def _release(self, stamp_ns: int) -> list[Increment]:
        """Emit what an observation message at ``stamp_ns`` makes final (none in the hold)."""
        state = self._state
        timely = state.samples[-1][0] - round(self.config.observation_delay_s * 1e9)
        if not state.hold_ended:
            if stamp_ns < timely:
                return []  # history from before this node matched its publisher: more may come
            state.hold_ended = f'at the first timely observation ({stamp_ns} ns)'
        return self._emit(horizon_ns=self._horizon())

    def _horizon(self) -> int:
        """The stamp up to which keyframes are final: the newest odometry less
        observation_delay_s; while the observation source has spoken within the last
        observation_silence_s of odometry, no later than its newest stamp either (a source
        that lags but keeps publishing is waited for, at most max_buffer_s)."""
        state = self._state
        latest = state.samples[-1][0]
        horizon = latest - round(self.config.observation_delay_s * 1e9)
        progress, spoke_at = state.progress_ns, state.progress_at_ns
        silence = round(self.config.observation_silence_s * 1e9)
        if progress is not None and spoke_at is not None and latest - spoke_at < silence:
            oldest = latest - round(self.config.max_buffer_s * 1e9)
            horizon = max(min(horizon, progress), oldest)
        return horizon

    def _hold_before_odometry(self, stamp_ns: int) -> None:
        """Keep an observation stamp that came before any odometry (at most max_buffer_s)."""
        pending = self._state.pending_stamps
        if stamp_ns not in pending:
            bisect.insort(pending, stamp_ns)
        horizon = pending[-1] - round(self.config.max_buffer_s * 1e9)
        old = [s for s in pending if s < horizon]
        if old:
            del pending[: len(old)]
            self.refused_stamps += len(old)
            self.warn(
                f'{len(old)} observation(s) held for odometry longer than max_buffer_s '
                f'(from {old[0]} ns): no odometry came; they get no keyframe'
            )

    def _release_before_odometry(self, first_ns: int) -> None:
        """The first odometry came: a held stamp at it gets the first keyframe, earlier none."""
        pending = self._state.pending_stamps
        early = [s for s in pending if s < first_ns]
        pending[:] = [s for s in pending if s > first_ns]
        if early:
            self.refused_stamps += len(early)
            self.warn(
                f'{len(early)} observation(s) from {early[0]} ns came before the first odometry '
                f'(at {first_ns} ns); they get no keyframe'
            )

    def flush(self) -> list[Increment]:
        """Emit every keyframe the odometry covers (at shutdown or at the end of a bag)."""
        if not self._state.samples:
            return []
        if not self._state.hold_ended:
            self._state.hold_ended = 'at a flush'
        return self._emit(horizon_ns=self._state.samples[-1][0], final=True)

    # -- keyframing -----------------------------------------------------------------------
    def _emit(self, horizon_ns: int, *, final: bool = False) -> list[Increment]:
        state = self._state
        out: list[Increment] = []
        if state.keyframe is None:
            return out
        samples = state.samples
        start = bisect.bisect_right(samples, state.keyframe[0], key=lambda sample: sample[0])
        for index in range(start, len(samples)):
            stamp, pose = samples[index]
            while state.pending_stamps and state.pending_stamps[0] <= min(stamp, horizon_ns):
                wanted = state.pending_stamps.pop(0)
                interpolated = interpolate_pose(wanted, samples[index - 1], samples[index])
                out.append(self._keyframe(wanted, interpolated))
            if stamp > horizon_ns:
                break
            last = final and index == len(samples) - 1 and stamp > state.keyframe[0]
            if last or (
                (state.checked_ns is None or stamp > state.checked_ns)
                and self._moved_enough(stamp, pose)
            ):
                out.append(self._keyframe(stamp, pose))
            elif stamp > state.keyframe[0]:
                state.checked_ns = (
                    stamp if state.checked_ns is None else max(stamp, state.checked_ns)
                )
        self._trim()
        return out

    def _moved_enough(self, stamp_ns: int, pose: FloatArray) -> bool:
        assert self._state.keyframe is not None
        last_stamp, last_pose = self._state.keyframe
        if stamp_ns <= last_stamp:
            return False
        config = self.config
        return bool(
            math.hypot(pose[0] - last_pose[0], pose[1] - last_pose[1])
            >= config.keyframe_distance_m
            or abs(math.remainder(pose[2] - last_pose[2], math.tau)) >= config.keyframe_angle_rad
            or (stamp_ns - last_stamp) / 1e9 >= config.keyframe_interval_s
        )

    def _keyframe(self, stamp_ns: int, pose: FloatArray) -> Increment:
        state = self._state
        assert state.keyframe is not None
        last_stamp, last_pose = state.keyframe
        if state.reset_pending:
            state.reset_pending = False
            increment = Increment(
                last_stamp,
                stamp_ns,
                np.zeros(3),
                np.diag(np.square(np.array(self.config.reset_sigma))),
                last_pose.copy(),
                pose.copy(),
                reset=True,
            )
        else:
            u = increment_between(last_pose[None], pose[None])[0]
            increment = Increment(
                last_stamp,
                stamp_ns,
                u,
                motion_covariance(self.config, u),
                last_pose.copy(),
                pose.copy(),
            )
        state.keyframe = (stamp_ns, pose.copy())
        state.checked_ns = None
        return increment

    def _reset(self, stamp_ns: int, pose: FloatArray, jump_m: float) -> list[Increment]:
        """Start a new odometry chain; bridge it to the old one with a weak zero increment."""
        state = self._state
        self.resets += 1
        self.warn(
            f'odometry reset at stamp {stamp_ns} ns (jump {jump_m:.2f} m); bridging with a '
            f'zero-motion increment'
        )
        out = self.flush()
        if state.keyframe is None:
            state.keyframe = (stamp_ns, pose.copy())
        state.samples = [(stamp_ns, pose)]
        state.pending_stamps = [s for s in state.pending_stamps if s > stamp_ns]
        state.reset_pending = True
        out.append(self._keyframe(stamp_ns, pose))
        return out

    def _rewind(self, stamp_ns: int, backwards_s: float) -> list[Increment]:
        """The clock went back: emit what the odometry covers, then wait for it to pass."""
        state = self._state
        out = self.flush()
        assert state.keyframe is not None
        state.rewound_until_ns = state.keyframe[0]
        state.rewound_dropped = 1
        self.dropped_samples += 1
        state.samples = []
        state.pending_stamps = []
        self.warn(
            f'odometry stamp went back {backwards_s:.2f} s (to {stamp_ns} ns): a restarted '
            f'base, a clock correction or a looped bag? Dropping odometry until its stamps pass '
            f'the last keyframe ({state.rewound_until_ns} ns); restart the mapper for a new '
            f'session'
        )
        return out

    def _after_rewind(self, stamp_ns: int, pose: FloatArray) -> list[Increment]:
        state = self._state
        assert state.rewound_until_ns is not None and state.keyframe is not None
        if stamp_ns <= state.rewound_until_ns:
            state.rewound_dropped += 1
            self.dropped_samples += 1
            return []
        self.resets += 1
        self.warn(
            f'odometry resumed at stamp {stamp_ns} ns after {state.rewound_dropped} samples '
            f'dropped behind the rewound clock; bridging with a zero-motion increment'
        )
        state.rewound_until_ns = None
        state.samples = [(stamp_ns, pose)]
        state.reset_pending = True
        return [self._keyframe(stamp_ns, pose)]

    def _trim(self) -> None:
        """Forget odometry older than the last keyframe (keep one sample before it)."""
        state = self._state
        if state.keyframe is None or len(state.samples) < 2:
            return
        stamps = [s for s, _ in state.samples]
        keep_from = max(bisect.bisect_right(stamps, state.keyframe[0]) - 1, 0)
        horizon = stamps[-1] - round(self.config.max_buffer_s * 1e9)
        keep_from = max(keep_from, bisect.bisect_left(stamps, horizon) - 1, 0)
        del state.samples[:keep_from]
