"""monoslam parameter values -> a validated MonoSlamConfig, target and node settings (ROS-free).

Every rejection raises ParameterError. Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from marker_detector.core.dictionaries import DEFAULT_DICTIONARY, DICTIONARIES
from monoslam_shadow_node.monoslam.core.monoslam_types import INITIALIZE_MODES, MonoSlamConfig
from monoslam_shadow_node.monoslam.known_points_input import KnownPointRows, read_known_points
from slam_core.arrays import FloatArray
from slam_core.params import (
    AT_LEAST_ONE,
    NON_NEGATIVE,
    POSITIVE,
    Param,
    ParamTable,
    config_param,
)

NODE_NAME = 'monoslam'
TARGET_CORNERS = 4
"""The target's corners are the known points 0-3 (OpenCV order TL, TR, BR, BL)."""
_CORE = MonoSlamConfig()


def _core(field: str, description: str, name: str = '') -> Param:
    return config_param(_CORE, field, description, name)


CORE_PARAMETERS = (
    _core(
        'known_points_source',
        "what fixes the world and its scale at the start: 'marker' (the target_* marker's "
        "corners, from fiducials), 'depth' (the features with a depth in the first depth "
        'image paired with a features frame: camera/depth/image_raw, registered to the colour '
        "image; the camera's optical frame then is map_frame) or 'file' (known_points_file)",
    ),
    _core(
        'depth_noise_per_m',
        "known_points_source 'depth': the depth sensor's noise, sigma_z = c z^2 (c in 1/m; "
        '1.425e-3 for structured light, Khoshelham and Elberink 2012)',
    ),
    _core(
        'depth_start_points',
        "known_points_source 'depth': most features the start puts in the map (>= 1)",
    ),
    _core('pixel_sigma_px', 'feature and target corner pixel noise per coordinate, px'),
    _core(
        'tracking_offset_px',
        "tracked features' persistent offsets per coordinate, px (0: white noise; "
        'otherwise each feature keeps its offset in the state)',
    ),
    _core('tracking_offset_time_s', 'their correlation time, s'),
    _core(
        'linear_acceleration_sigma',
        'constant velocity model: linear acceleration noise, m/s^2 per sqrt(Hz)',
        'linear_acceleration_sigma_m_s2',
    ),
    _core(
        'angular_acceleration_sigma',
        'constant velocity model: angular acceleration noise, rad/s^2 per sqrt(Hz)',
        'angular_acceleration_sigma_rad_s2',
    ),
    _core('initial_velocity_sigma_m_s', 'camera velocity std. dev. at the start, m/s'),
    _core(
        'initial_angular_velocity_sigma_rad_s',
        'camera angular velocity std. dev. at the start, rad/s',
    ),
    _core(
        'initial_inverse_depth',
        'inverse depth a new feature starts at (initialize=all), 1/m',
        'initial_inverse_depth_per_m',
    ),
    _core(
        'initial_inverse_depth_sigma',
        'its standard deviation, 1/m',
        'initial_inverse_depth_sigma_per_m',
    ),
    _core(
        'second_order',
        "an inverse-depth feature's innovation covariance takes the product of its inverse "
        "depth's and its baseline's uncertainties, which the EKF's linearization drops "
        '(docs/design/monoslam.md)',
    ),
    _core('gate_probability', 'chi-square gate of a measurement (2 dof)'),
    _core(
        'linearity_threshold',
        'an inverse-depth feature whose linearity index is below this becomes Euclidean',
    ),
    _core('max_features', 'most features in the filter'),
    _core('target_measured', 'initialize=all: add features while fewer are measured'),
    _core('max_new_per_frame', 'initialize=all: most features added per frame'),
    _core('min_new_spacing_px', 'initialize=all: new features at least this far apart, px'),
    _core(
        'max_view_angle_deg',
        'a map feature is searched for only within this angle of its first viewing ray, deg',
    ),
    _core('view_margin_px', 'a map feature is searched for only this far inside the image, px'),
    _core('failure_window', 'measurement attempts a feature is judged over'),
    _core('min_success_ratio', 'a feature accepted less often over them is deleted'),
    _core('max_consecutive_failures', 'a feature rejected this often in a row is deleted'),
    _core('lost_after_frames', 'tracking is lost after this many frames measuring nothing'),
    _core(
        'lost_after_known_rejected_frames',
        'tracking is lost after this many frames in a row in which the gate rejected most '
        'known points in view',
    ),
    _core('max_position_sigma_m', 'tracking is lost when the position std. dev. exceeds it, m'),
    _core('max_gap_s', 'a longer gap between frames is logged as a warning, s'),
    Param(
        'initialize',
        'handover',
        "'handover': features enter only when the Shadow filter hands them over as static "
        "(shadow/static_features); 'all': classic MonoSLAM, from every new track",
        choices=INITIALIZE_MODES,
        field='initialize',
    ),
    _core(
        'handover_probation',
        'a handed-over feature corrects only itself (a Schmidt consider update), not the '
        'camera, until its inverse depth becomes Euclidean (or while fewer than 5 others are '
        'measured in a frame)',
    ),
    _core(
        'fill_undecided',
        "with initialize 'handover': when fewer than target_measured features are measured, "
        'features the Shadow filter has not decided on fill the map; DYNAMIC in '
        'shadow/tracks: out',
    ),
    _core(
        'undecided_probation',
        'fill_undecided: such a feature corrects only itself (a consider update, never the '
        'camera) until the Shadow filter hands it over as static',
    ),
    _core(
        'new_probation',
        "initialize 'all': a new feature corrects only itself (a consider update) until its "
        'inverse depth becomes Euclidean, as a handover does',
    ),
    _core(
        'update',
        "'ransac': 1-point RANSAC update (Civera et al. 2010: the best one-match hypothesis "
        "picks the low-innovation inliers, gated high-innovation ones are rescued); 'gated': "
        'every measurement inside the chi-square gate',
    ),
    _core('ransac_seed', 'seed of the 1-point RANSAC draws: runs are reproducible'),
    _core(
        'estimate_noise',
        "the tracker's noise estimated online from the tracks SLAM measures (each against its "
        'point fixed over the track) and taken once a second: white sigma at least '
        'pixel_sigma_px, offsets that persist when they matter (else tracking_offset_px); the '
        'declared values until the estimate is confident',
    ),
)


def _frame_rule(frame: str) -> str | None:
    if not frame.strip() or frame.startswith('/'):
        return 'must name a frame (no leading slash)'
    return None


def _file_rule(path: str) -> str | None:
    if path.strip() and Path(path).expanduser().is_dir():
        return 'is a directory; name a file'
    return None


TARGET_PARAMETERS = (
    Param('target_id', 0, 'marker id of the initialization target', range=NON_NEGATIVE),
    Param(
        'target_dictionary',
        DEFAULT_DICTIONARY,
        'cv2.aruco dictionary of the target, as marker_detector names it',
        choices=tuple(DICTIONARIES),
    ),
    Param(
        'target_size_m',
        0.16,
        "side of the target's black square, m (marker_detector's default marker size)",
        range=POSITIVE,
    ),
    Param(
        'target_xyz_m',
        [0.0, 0.0, 0.0],
        'target centre in map_frame, m (the marker frame: x right, y up, z out of the face)',
        length=3,
    ),
    Param(
        'target_rpy_rad',
        [0.0, 0.0, 0.0],
        'target orientation in map_frame: roll, pitch, yaw (fixed axes X, Y, Z), rad',
        length=3,
    ),
)
NODE_PARAMETERS = (
    Param(
        'map_frame',
        'monoslam_map',
        "frame of the pose, path, map and TF (the target defines it; not the robot's map)",
        validator=_frame_rule,
    ),
    Param('publish_tf', False, 'publish map_frame -> tf_camera_frame on /tf'),
    Param(
        'tf_camera_frame',
        'monoslam_camera',
        'child frame of that TF: the camera as MonoSLAM places it, under its own name (the '
        "camera's optical frame has its parent in the robot's tree)",
        validator=_frame_rule,
    ),
    Param(
        'publish_predictions',
        False,
        'publish features/predicted (predicted pixels of owned features) per camera_info',
    ),
    Param('path_length', 3000, 'poses kept in monoslam/path, the latest', range=AT_LEAST_ONE),
    Param(
        'map_period_s',
        1.0,
        'monoslam/map is published at most this often, s',
        range=POSITIVE,
    ),
    Param(
        'stamp_tolerance_s',
        0.0,
        'largest stamp difference between features and the fiducials they pair with, s',
        range=NON_NEGATIVE,
    ),
    Param(
        'sync_horizon_s',
        0.5,
        'a features frame waits for its fiducials until a later one comes, or until this much '
        'stamp time of frames came with no fiducials at all, s (> stamp_tolerance_s)',
    ),
    Param(
        'known_points_file',
        '',
        "known_points_source 'file': CSV 'id,x,y,z,u,v' (header first): each known point's "
        'position in map_frame (m) and its raw pixel in the first image; the track nearest '
        'each pixel (within known_points_match_px) in the first frame becomes that point',
        validator=_file_rule,
    ),
    Param(
        'known_points_match_px',
        3.0,
        "known_points_file: how far a track may be from a row's pixel, px",
        range=POSITIVE,
    ),
    Param(
        'depth_stamp_tolerance_s',
        0.02,
        "known_points_source 'depth': largest features-to-depth image stamp difference, s "
        "(TUM's association: an RGB-D camera's colour and depth images are up to 1/60 s apart)",
        range=POSITIVE,
    ),
    Param(
        'queue_size',
        100,
        'feature frames and fiducial arrays held while waiting',
        range=AT_LEAST_ONE,
    ),
    Param(
        'trajectory_file',
        '',
        'write the trajectory (TUM text) here on shutdown; empty: none',
        validator=_file_rule,
    ),
    Param(
        'checkpoint_period_s',
        10.0,
        'save the map to checkpoint_file this often when it changed (and on shutdown), s; '
        '0 = only on ~/save_map',
        range=NON_NEGATIVE,
    ),
    Param(
        'checkpoint_file',
        '',
        "where the map's checkpoint goes (.npz, written atomically); '' = no checkpoints",
        validator=_file_rule,
    ),
    Param(
        'resume_from',
        '',
        "checkpoint to start from; '' = a fresh start, 'auto' = checkpoint_file if it exists",
        validator=_file_rule,
    ),
)
PARAMETERS = ParamTable(NODE_NAME, (*CORE_PARAMETERS, *TARGET_PARAMETERS, *NODE_PARAMETERS))


@dataclass(frozen=True, eq=False)
class TargetSettings:
    """The target: marker id, dictionary, side (m), centre (3,) m and R_map_marker (3, 3)."""

    marker_id: int
    dictionary: str
    size_m: float
    centre_m: FloatArray
    rotation: FloatArray

    @property
    def corners_m(self) -> FloatArray:
        """The black square's corners (4, 3) m in map, OpenCV order TL, TR, BR, BL."""
        half = 0.5 * self.size_m
        local = np.array(
            [[-half, half, 0.0], [half, half, 0.0], [half, -half, 0.0], [-half, -half, 0.0]]
        )
        return np.asarray(self.centre_m + local @ self.rotation.T, dtype=np.float64)

    def known_points(self) -> dict[int, tuple[float, float, float]]:
        """Return the corners as the filter's known points: key = corner index 0-3."""
        return {k: (float(x), float(y), float(z)) for k, (x, y, z) in enumerate(self.corners_m)}

    def describe(self) -> str:
        """Return 'id 0 (DICT_APRILTAG_36h11, 0.6 m) at (x, y, z) m' for the log."""
        x, y, z = (float(v) for v in self.centre_m)
        return (
            f'id {self.marker_id} ({self.dictionary}, {self.size_m:g} m) at '
            f'({x:g}, {y:g}, {z:g}) m'
        )


@dataclass(frozen=True)
class NodeSettings:
    """The node's own settings (frames, outputs, stamp sync, files); times in int ns or s."""

    map_frame: str
    publish_tf: bool
    tf_camera_frame: str
    publish_predictions: bool
    path_length: int
    map_period_s: float
    stamp_tolerance_ns: int
    sync_horizon_ns: int
    queue_size: int
    trajectory_file: Path | None
    checkpoint_period_s: float = 10.0
    checkpoint_file: Path | None = None
    resume_from: str = ''
    known_points_match_px: float = 3.0
    depth_stamp_tolerance_ns: int = 20_000_000


def target_settings(values: Mapping[str, Any]) -> TargetSettings:
    """Validate the target's parameters (raises ParameterError)."""
    checked = PARAMETERS.validate(values)
    rpy = checked['target_rpy_rad']
    rotation = Rotation.from_euler('xyz', rpy).as_matrix()  # R = Rz(yaw) Ry(pitch) Rx(roll)
    return TargetSettings(
        checked['target_id'],
        checked['target_dictionary'],
        checked['target_size_m'],
        np.array(checked['target_xyz_m']),
        rotation,
    )


def known_point_rows(values: Mapping[str, Any]) -> KnownPointRows | None:
    """Read known_points_file for the 'file' source (else None); ParameterError on a problem."""
    checked = PARAMETERS.validate(values)
    path = checked['known_points_file'].strip()
    if checked['known_points_source'] != 'file':
        return None
    if not path:
        raise PARAMETERS.fail('known_points_file', path, "needed with known_points_source 'file'")
    try:
        return read_known_points(Path(path).expanduser())
    except ValueError as error:
        raise PARAMETERS.fail('known_points_file', path, str(error)) from error


def monoslam_config(
    values: Mapping[str, Any], target: TargetSettings, rows: KnownPointRows | None = None
) -> MonoSlamConfig:
    """Validate the filter's parameters into a MonoSlamConfig; raises ParameterError."""
    fields = PARAMETERS.fields(PARAMETERS.validate(values))
    known = rows.known_points() if rows is not None else target.known_points()
    return PARAMETERS.build(lambda: MonoSlamConfig(known_points=known, **fields))


def node_settings(values: Mapping[str, Any]) -> NodeSettings:
    """Validate the node's own parameters (raises ParameterError)."""
    checked = PARAMETERS.validate(values)
    tolerance = checked['stamp_tolerance_s']
    horizon = checked['sync_horizon_s']
    if horizon <= tolerance:
        raise PARAMETERS.fail(
            'sync_horizon_s', horizon, f'must exceed stamp_tolerance_s ({tolerance} s)'
        )
    if checked['tf_camera_frame'] == checked['map_frame']:
        raise PARAMETERS.fail(
            'tf_camera_frame', checked['tf_camera_frame'], 'must differ from map_frame'
        )
    trajectory, checkpoint = checked['trajectory_file'], checked['checkpoint_file']
    return NodeSettings(
        map_frame=checked['map_frame'],
        publish_tf=checked['publish_tf'],
        tf_camera_frame=checked['tf_camera_frame'],
        publish_predictions=checked['publish_predictions'],
        path_length=checked['path_length'],
        map_period_s=checked['map_period_s'],
        stamp_tolerance_ns=round(tolerance * 1e9),
        sync_horizon_ns=round(horizon * 1e9),
        queue_size=checked['queue_size'],
        trajectory_file=Path(trajectory).expanduser() if trajectory.strip() else None,
        checkpoint_period_s=checked['checkpoint_period_s'],
        checkpoint_file=Path(checkpoint).expanduser() if checkpoint.strip() else None,
        resume_from=checked['resume_from'].strip(),
        known_points_match_px=checked['known_points_match_px'],
        depth_stamp_tolerance_ns=round(checked['depth_stamp_tolerance_s'] * 1e9),
    )
