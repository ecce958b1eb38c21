"""em_sam_mapper: EM-SAM batch mapping with moveable-landmark detection (paper 000).

Collects odometry increments and landmark observations and re-solves EM-SAM on a timer
(warm-started) and on request; publishes the trajectory, the landmark map with EM weights,
the moveable landmarks with every sighting (most recent first), the paper's Fig. 5 markers
and TF map->odom; writes a report (JSON and PNG, atomically) on request and on shutdown.
With ``mode: localization`` it holds the static landmarks of a saved map fixed.

Topics:
  subscribes  odometry_increments (OdometryIncrement, reliable, 1000, transient-local),
              landmark_observations (LandmarkObservationArray, reliable, 1000)
  publishes   em_sam/path, em_sam/landmarks, em_sam/moveable, em_sam/moveable_online,
              em_sam/markers (reliable, transient-local, 1); em_sam/pose (PoseWithCovariance-
              Stamped); /tf (map->odom); /diagnostics (inputs, solves, lag)
Services: ~/optimize, ~/write_report, ~/save_map (std_srvs/Trigger), ~/find_landmark
(slam_interfaces/FindLandmark: sightings, most recent first), ~/load_map
(slam_interfaces/LoadMap: localize on a saved map).
Frames: the map frame is the odometry frame at the first keyframe (in localization, the saved
map's). Parameters: ``em_sam_mapper --help``. In full: docs/design/em_sam_nodes.md.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Path as PathMessage
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.timer import Timer
from std_srvs.srv import Trigger
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import MarkerArray

from em_sam_node.core.factorization import SingularSystemError
from em_sam_node.mapper.checkpoint import load_checkpoint, save_checkpoint
from em_sam_node.mapper.conversions import (
    increment_from_message,
    observations_from_message,
)
from em_sam_node.mapper.map_files import MAP_FILE, MapFileError, known_map, read_map, write_map
from em_sam_node.mapper.outputs import (
    landmark_map_message,
    map_to_odom_tf,
    markers_message,
    moveable_message,
    path_message,
    pose_message,
    sighting_messages,
)
from em_sam_node.mapper.processor import MapperProcessor
from em_sam_node.mapper.report import write_report
from em_sam_node.mapper.settings import PARAMETERS, config_from_parameters
from slam_core import lazy_stats
from slam_core.cli import console_main
from slam_core.errors import ParameterError
from slam_core.files import keep_previous_run
from slam_interfaces.msg import (
    LandmarkMap,
    LandmarkObservationArray,
    MoveableLandmark,
    MoveableLandmarkArray,
    OdometryIncrement,
)
from slam_interfaces.srv import FindLandmark, LoadMap
from slam_ros.diagnostics import Diagnostics
from slam_ros.params import declare_parameters
from slam_ros.qos import latched_qos, output_qos, replayed_qos
from slam_ros.spin import spin_node


class MapperBehaviour(Node):
    """em_sam_mapper on an rclpy node, plain (EmSamMapperNode) or lifecycle."""

    def _configure(self, values: dict[str, Any]) -> None:
        self._active: list[Any] = []
        self.mapper = MapperProcessor(config_from_parameters(values), warn=self._warn)
        self.map_start = (
            bool(values['map_start_at_dock']),
            tuple(float(v) for v in values['map_start_pose']),
            tuple(float(v) for v in values['map_start_sigma']),
        )
        if values['mode'] == 'localization':
            if not values['map_file']:
                raise ParameterError(
                    "parameter em_sam_mapper.map_file='': mode localization needs it (the "
                    'em_sam_map.yaml that a mapping run wrote beside its checkpoint)'
                )
            self.get_logger().info(self.load_map(str(values['map_file'])))
        self.optimize_period_s = float(values['optimize_period_s'])
        self.map_frame = str(values['map_frame'])
        self.odom_frame = str(values['odom_frame'])
        self.report_dir = Path(values['report_dir']).expanduser() if values['report_dir'] else None
        if self.report_dir is not None and not values['resume_from']:
            self._keep_previous_run(self.report_dir)
        self.checkpoint_file = self._checkpoint_path(str(values['checkpoint_file']))
        self.checkpoint_period_s = float(values['checkpoint_period_s'])
        self._saved_state: tuple[int, ...] | None = None
        self.solves = 0
        self.poses_undetermined = 0  # solves whose latest pose had no marginal (em_sam/pose)
        self.unsolved = 0  # solves refused: the system was not determined
        self._online_moveable: frozenset[int] = frozenset()
        self._resume(str(values['resume_from']))

        latched = latched_qos()
        self.path_publisher = self.create_publisher(PathMessage, 'em_sam/path', latched)
        self.map_publisher = self.create_publisher(LandmarkMap, 'em_sam/landmarks', latched)
        self.moveable_publisher = self.create_publisher(
            MoveableLandmarkArray, 'em_sam/moveable', latched
        )
        self.marker_publisher = self.create_publisher(MarkerArray, 'em_sam/markers', latched)
        self.online_publisher = self.create_publisher(
            MoveableLandmarkArray, 'em_sam/moveable_online', latched
        )
        self.tf_publisher = self.create_publisher(TFMessage, '/tf', output_qos(depth=100))
        self.pose_publisher = self.create_publisher(
            PoseWithCovarianceStamped, 'em_sam/pose', output_qos()
        )
        self.diagnostics = Diagnostics(self, self._counts)
        self.create_service(Trigger, '~/optimize', self._on_optimize)
        self.create_service(Trigger, '~/write_report', self._on_write_report)
        self.create_service(FindLandmark, '~/find_landmark', self._on_find_landmark)
        self.create_service(Trigger, '~/save_map', self._on_save_map)
        self.create_service(LoadMap, '~/load_map', self._on_load_map)
        # a resumed solution has no sightings: the next solve (warm-started from it) makes them
        self._dirty = self.mapper.result is not None
        self._next_solve = 0.0  # time.monotonic() before which the timer does not solve

    def _activate(self, values: dict[str, Any]) -> None:
        """Take inputs and run the timers."""
        timed = self.diagnostics.timed
        tf_period_s = float(values['tf_period_s'])
        subscription = self.create_subscription(
            OdometryIncrement,
            'odometry_increments',
            timed(self._on_increment, 'odometry_increments'),
            replayed_qos(1000) if values['increments_transient_local'] else output_qos(1000),
        )
        observations = self.create_subscription(
            LandmarkObservationArray,
            'landmark_observations',
            timed(self._on_observations, 'landmark_observations'),
            replayed_qos(1000) if values['observations_transient_local'] else output_qos(1000),
        )
        self._active += [subscription, observations]
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        if self.checkpoint_period_s > 0 and self.checkpoint_file is not None:
            checkpoint = timed(self._on_checkpoint)
            self._active.append(
                self.create_timer(self.checkpoint_period_s, checkpoint, clock=steady)
            )
        if self.optimize_period_s > 0:
            solve = timed(self._on_timer)
            self._active.append(self.create_timer(self.optimize_period_s, solve, clock=steady))
        self._active.append(self.create_timer(tf_period_s, timed(self._publish_tf), clock=steady))

    def _deactivate(self) -> None:
        """Stop taking inputs and running the timers; what is held stays."""
        for entity in self._active:
            if isinstance(entity, Timer):
                self.destroy_timer(entity)
            else:
                self.destroy_subscription(entity)
        self._active = []

    def _counts(self) -> dict[str, int]:
        """The counts on /diagnostics (inputs, drops, solves)."""
        mapper = self.mapper
        last = mapper.online_last
        return {
            'keyframes': len(mapper.stamps_ns),
            'observations': len(mapper.observations),
            'pending observations': len(mapper.pending),
            'dropped': mapper.dropped_increments + mapper.dropped_observations,
            'dropped increments': mapper.dropped_increments,
            'dropped observations': mapper.dropped_observations,
            'before first keyframe': mapper.before_start_observations,
            'already held': mapper.duplicate_increments + mapper.duplicate_observations,
            'solves': self.solves,
            'solves not determined': self.unsolved,
            'poses not determined': self.poses_undetermined,
            'online keyframes': mapper.online.num_keyframes if mapper.online else 0,
            # beyond the smoother's horizon: marginalized, their late sightings not smoothed
            'online keyframes marginalized': mapper.online.kept_from if mapper.online else 0,
            'online late sightings dropped': mapper.online.dropped_late if mapper.online else 0,
            'online observations waiting': mapper.online_waiting,
            'online update ms (last)': round(1e3 * last.seconds) if last else 0,
            'online update ms (max)': round(1e3 * mapper.online_max_s),
            'online moveable': len(mapper.online_moveable),
            'online failures': len(mapper.online_failures),
        }

    def _keep_previous_run(self, report_dir: Path) -> None:
        """A fresh run does not overwrite the last one's report and checkpoint."""
        moved = keep_previous_run(report_dir, 'em_sam_')
        if moved is not None:
            self.get_logger().info(
                f'the previous run in {str(report_dir)!r} was moved to {str(moved)!r}'
            )
        elif any(report_dir.glob('em_sam_*')):
            self.get_logger().warning(
                f'{str(report_dir)!r} holds other files too: the em_sam_* files of the '
                'previous run there will be replaced (give report_dir a directory of its own)'
            )

    def _warn(self, message: str) -> None:
        self.get_logger().warning(message, throttle_duration_sec=2.0)

    # -- checkpoints ----------------------------------------------------------------------
    def _checkpoint_path(self, text: str) -> Path | None:
        if text:
            return Path(text).expanduser()
        return None if self.report_dir is None else self.report_dir / 'em_sam_checkpoint.npz'

    def _resume(self, resume_from: str) -> None:
        if not resume_from:
            return
        path = Path(resume_from).expanduser() if resume_from != 'auto' else self.checkpoint_file
        if path is None or (resume_from == 'auto' and not path.exists()):
            self.get_logger().info(
                f'resume_from auto: no checkpoint at {str(path)!r}; fresh start'
            )
            return
        load_checkpoint(self.mapper, path)
        self._saved_state = self._state_key()
        mapper = self.mapper
        self.get_logger().info(
            f'resumed from {str(path)!r}: {mapper.num_keyframes} keyframes, '
            f'{len(mapper.observations)} observations, {len(mapper.pending)} pending, '
            f'solution of {mapper.result_keyframes} keyframes'
        )

    def _state_key(self) -> tuple[int, ...]:
        mapper = self.mapper
        return (
            mapper.num_keyframes,
            len(mapper.seen_observations),
            mapper.result_keyframes,
            self.solves,
            mapper.dropped_increments,
        )

    def save_checkpoint(self) -> str:
        """Write the state to checkpoint_file; return a one-line summary."""
        if self.checkpoint_file is None:
            return 'no checkpoint_file (and no report_dir) is set'
        save_checkpoint(self.mapper, self.checkpoint_file)
        self._saved_state = self._state_key()
        readable = ''
        result = self.mapper.result
        if result is not None:  # the solved map beside it, readable without numpy
            stamps = np.array(self.mapper.stamps_ns[: self.mapper.result_keyframes])
            joint = self.mapper.static_joint_covariance()
            write_map(result, stamps, self.checkpoint_file.parent, self.map_frame, joint)
            readable = f' (and the map as {MAP_FILE} with CSVs beside it)'
        return (
            f'checkpoint of {self.mapper.num_keyframes} keyframes, '
            f'{len(self.mapper.observations)} observations written to '
            f'{str(self.checkpoint_file)!r}{readable}'
        )

    def _on_checkpoint(self) -> None:
        if self._state_key() != self._saved_state:
            self.get_logger().debug(self.save_checkpoint())

    def _on_save_map(self, request: Trigger.Request, response: Trigger.Response) -> Any:
        try:
            response.message = self.save_checkpoint()
            response.success = self.checkpoint_file is not None
        except OSError as err:
            response.success, response.message = False, f'could not write the checkpoint: {err}'
        return response

    def load_map(self, map_file: str) -> str:
        """Localize on the saved map ``map_file`` from now on; return a one-line summary.

        Raises:
            MapFileError: the map cannot be read or holds no usable static landmark.
        """
        path = Path(map_file).expanduser()
        saved = read_map(path)
        fixed = known_map(saved, path)
        at_dock, start_pose, sigma = self.map_start
        if at_dock and len(saved.poses):
            start_pose = tuple(float(v) for v in saved.poses[0])
        self.mapper.use_map(fixed, start_pose, sigma)  # type: ignore[arg-type]
        self._dirty = self.mapper.num_keyframes >= 2
        x, y, theta = start_pose
        return (
            f'localizing on {str(path)!r}: {len(fixed.landmark_ids)} static landmarks held '
            f'fixed (frame {saved.frame_id!r}), start at ({x:.3f} m, {y:.3f} m, '
            f'{theta:.3f} rad)' + (" (the map's first pose)" if at_dock else '')
        )

    def _on_load_map(self, request: Any, response: Any) -> Any:
        try:
            response.message = self.load_map(str(request.map_file))
        except (MapFileError, OSError) as err:
            response.success, response.message = False, str(err)
            self.get_logger().error(f'~/load_map: {err}')
            return response
        self.get_logger().info(response.message)
        response.success = True
        assert self.mapper.config.known_map is not None
        response.landmarks = len(self.mapper.config.known_map.landmark_ids)
        return response

    # -- inputs ---------------------------------------------------------------------------
    def _on_increment(self, message: OdometryIncrement) -> None:
        self.mapper.add_increment(increment_from_message(message))
        self._dirty = True
        self._online_changes()

    def _online_changes(self) -> None:
        """Log and publish the online moveable set when it changes (kept while the smoother
        is rebuilt or stopped)."""
        if self.mapper.online is None:
            return
        moveable = self.mapper.online_moveable
        if moveable != self._online_moveable:
            added = sorted(moveable - self._online_moveable)
            cleared = sorted(self._online_moveable - moveable)
            smoothed = self.mapper.online.num_keyframes if self.mapper.online else 0
            self.get_logger().info(
                f'online, keyframe {smoothed}: moveable {sorted(moveable)}'
                + (f' (new {added})' if added else '')
                + (f' (cleared {cleared})' if cleared else '')
            )
            self._online_moveable = moveable
            self.online_publisher.publish(self._online_message(moveable))

    def _online_message(self, moveable: frozenset[int]) -> MoveableLandmarkArray:
        """The online moveable set with each landmark's weight and sightings."""
        message = MoveableLandmarkArray()
        message.header.frame_id = self.map_frame
        message.header.stamp = self.get_clock().now().to_msg()
        assert self.mapper.online is not None
        weights = self.mapper.online.weights
        for landmark_id in sorted(moveable):
            entry = MoveableLandmark()
            entry.landmark_id, entry.weight = landmark_id, float(weights[landmark_id])
            sightings = self.mapper.online_sightings(landmark_id)
            entry.sightings = sighting_messages(sightings) if sightings is not None else []
            message.landmarks.append(entry)
        return message

    def _on_observations(self, message: LandmarkObservationArray) -> None:
        for observation in observations_from_message(message):
            self.mapper.add_observation(observation)
            self._dirty = True

    # -- solving and publishing -----------------------------------------------------------
    def _on_timer(self) -> None:
        if self._dirty and time.monotonic() >= self._next_solve:
            self.optimize()

    def optimize(self) -> str:
        """Solve EM-SAM now and publish the results; return a one-line summary. The timer's
        next solve waits as long as this one took (docs/design/em_sam_nodes.md)."""
        started = time.perf_counter()
        try:
            result = self.mapper.optimize()
        except SingularSystemError as error:  # e.g. an increment whose covariance is so wide
            self._dirty = False  # that it fixes nothing: solved again once new data come
            self.unsolved += 1
            self.get_logger().warning(f'EM-SAM not solved: {error}')
            return f'not solved: {error}'
        finally:
            self._next_solve = time.monotonic() + (time.perf_counter() - started)
        # only once solved: a solve cut short (Ctrl-C) leaves the report to solve again
        self._dirty = False
        if result is None:
            return 'not enough data to optimize'
        self.solves += 1
        stamp = self.get_clock().now().to_msg()
        stamps = np.array(self.mapper.stamps_ns[: self.mapper.result_keyframes])
        self.path_publisher.publish(path_message(result, stamps, self.map_frame, stamp))
        self.map_publisher.publish(landmark_map_message(result, self.map_frame, stamp))
        self.moveable_publisher.publish(moveable_message(result, self.map_frame, stamp))
        self.marker_publisher.publish(markers_message(result, self.map_frame, stamp))
        try:
            latest = self.mapper.latest_pose()
        except SingularSystemError as error:  # the solve's latest keyframe is not determined
            latest = None
            self.poses_undetermined += 1
            self.get_logger().warning(f'em_sam/pose not published for this solve: {error}')
        if latest is not None:
            self.pose_publisher.publish(pose_message(*latest, self.map_frame))
        self._publish_tf()
        where = ', on the saved map' if self.mapper.config.localizing else ''
        summary = (
            f'EM-SAM ({result.mode}{where}): {len(stamps)} keyframes, {len(result.landmark_ids)} '
            f'landmarks, moveable {result.landmark_ids[result.moveable].tolist()}, '
            f'{result.em_iterations} EM iterations in {time.perf_counter() - started:.3f} s'
        )
        if result.mode == 'robust':
            translation, rotation = result.odometry_calibration
            summary += (
                f', odometry calibration: translation x{translation:.3f}, rotation x{rotation:.3f}'
            )
        self.get_logger().info(summary)
        return summary

    def _publish_tf(self) -> None:
        transform = self.mapper.map_to_odom()
        if transform is not None:
            stamp = self.get_clock().now().to_msg()
            self.tf_publisher.publish(
                map_to_odom_tf(transform, self.map_frame, self.odom_frame, stamp)
            )

    def write_report(self) -> list[Path]:
        """Solve if needed and write the report; return the files written."""
        if self.report_dir is None:
            return []
        if self._dirty or self.mapper.result is None:
            # Solve without publishing: on shutdown the ROS context may be gone already.
            self._dirty = False
            self.mapper.optimize()
        result = self.mapper.result
        if result is None:
            self.get_logger().warning('no report written: nothing was solved')
            return []
        stamps = np.array(self.mapper.stamps_ns[: self.mapper.result_keyframes])
        extra = {
            'dropped_observations': self.mapper.dropped_observations,
            'observations_before_first_keyframe': self.mapper.before_start_observations,
            'parameters': {s.name: self.get_parameter(s.name).value for s in PARAMETERS},
        }
        paths = write_report(result, stamps, self.report_dir, extra)
        self.get_logger().info(f'report written to {str(self.report_dir)!r}')
        return paths

    # -- services -------------------------------------------------------------------------
    def _on_optimize(self, request: Trigger.Request, response: Trigger.Response) -> Any:
        response.message = self.optimize()
        response.success = self.mapper.result is not None
        return response

    def _on_write_report(self, request: Trigger.Request, response: Trigger.Response) -> Any:
        if self.report_dir is None:
            response.success, response.message = False, 'report_dir is not set'
            return response
        paths = self.write_report()
        response.success = bool(paths)
        response.message = ', '.join(str(p) for p in paths) or 'nothing to report yet'
        return response

    def _on_find_landmark(self, request: Any, response: Any) -> Any:
        if self._dirty or self.mapper.result is None:
            self.optimize()
        sightings = self.mapper.find_landmark(int(request.landmark_id))
        response.frame_id = self.map_frame
        if sightings is None:
            response.found = False
            response.message = f'landmark {request.landmark_id} has never been observed'
            return response
        result = self.mapper.result
        assert result is not None
        index = int(np.flatnonzero(result.landmark_ids == request.landmark_id)[0])
        response.found = True
        response.moveable = bool(result.moveable[index])
        response.weight = float(result.weights[index])
        response.sightings = sighting_messages(sightings)
        response.message = f'{len(response.sightings)} sightings, most recent first'
        return response

    def destroy_node(self) -> None:
        """Write the final report (and checkpoint) before going away."""
        self._finalize()
        super().destroy_node()

    def _finalize(self) -> None:
        """Write the report, and the checkpoint when anything was received."""
        try:
            self.write_report()
        except Exception as err:  # a report must never prevent the node from shutting down
            self.get_logger().error(f'could not write the report: {err}')
        if self.mapper.num_keyframes == 0 and not self.mapper.observations:
            self.get_logger().info('no checkpoint written: nothing was received')
        elif self.checkpoint_period_s > 0 and self.checkpoint_file is not None:
            try:
                self.save_checkpoint()
            except Exception as err:
                self.get_logger().error(f'could not write the checkpoint: {err}')


class EmSamMapperNode(MapperBehaviour):
    """em_sam_mapper as a plain node: configured and active from the start."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('em_sam_mapper', **kwargs)
        values = declare_parameters(self, PARAMETERS)
        lazy_stats.load()
        self._configure(values)
        self._activate(values)


@console_main('em_sam_mapper')
def main(argv: list[str] | None = None) -> int:
    """Run the node until Ctrl-C; the report is written on the way out."""
    return spin_node('em_sam_mapper', EmSamMapperNode, argv, parameters=PARAMETERS, doc=__doc__)


if __name__ == '__main__':
    sys.exit(main())
