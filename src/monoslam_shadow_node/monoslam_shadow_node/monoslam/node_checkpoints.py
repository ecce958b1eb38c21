"""The monoslam node's checkpoints: resume at start; save periodically, on ~/save_map, at exit."""

from __future__ import annotations

from pathlib import Path as FilePath
from typing import TYPE_CHECKING, Any

from std_srvs.srv import Trigger

from monoslam_shadow_node.monoslam.checkpoint import load_checkpoint, save_checkpoint
from monoslam_shadow_node.monoslam.conversions import PoseFields
from monoslam_shadow_node.monoslam.processor import MonoSlamProcessor
from monoslam_shadow_node.monoslam.settings import NodeSettings


class CheckpointsMixin:
    """Checkpoint handling for ``MonoSlamNode`` (an rclpy Node with these attributes)."""

    settings: NodeSettings
    processor: MonoSlamProcessor
    trajectory: list[PoseFields]
    _saved_state: tuple[int, ...] | None

    if TYPE_CHECKING:  # provided by rclpy's Node

        def get_logger(self) -> Any: ...

    def _resume(self, resume_from: str) -> None:
        if not resume_from:
            return
        file = self.settings.checkpoint_file
        path = file if resume_from == 'auto' else FilePath(resume_from).expanduser()
        if path is None or (resume_from == 'auto' and not path.exists()):
            self.get_logger().info(
                f'resume_from auto: no checkpoint at {str(path)!r}; fresh start'
            )
            return
        self.trajectory = load_checkpoint(self.processor, path)
        self._saved_state = self._state_key()
        slam, last_ns = self.processor.slam, self.processor.sync.last_ns
        points = len(slam.map_points()) if slam is not None else 0
        self.get_logger().info(
            f'resumed from {str(path)!r}: {self.processor.status}, {points} map points, '
            f'last frame at stamp {last_ns} ns; the first frame after it decides whether to '
            'predict over the gap or re-localise from the target'
        )

    def _state_key(self) -> tuple[int, ...]:
        counts = self.processor.counts
        return (counts.features_received, counts.fiducials_received, counts.processed,
                counts.accepted, counts.refused, counts.dropped_total)  # fmt: skip

    def save_checkpoint(self) -> str:
        """Write checkpoint_file; return a summary. Raises ValueError (no camera yet), OSError."""
        path = self.settings.checkpoint_file
        if path is None:
            return 'no checkpoint_file is set'
        save_checkpoint(self.processor, path, self.trajectory)
        self._saved_state = self._state_key()
        points = len(self.processor.map_points())
        return (
            f'checkpoint of {self.processor.counts.processed} frames, {points} map points '
            f'({self.processor.status}) written to {str(path)!r}'
        )

    def _on_checkpoint(self) -> None:
        if self.processor.slam is not None and self._state_key() != self._saved_state:
            try:
                self.get_logger().debug(self.save_checkpoint())
            except OSError as err:
                self.get_logger().error(f'could not write the checkpoint: {err}')

    def _on_save_map(self, request: Trigger.Request, response: Trigger.Response) -> Any:
        try:
            response.message = self.save_checkpoint()
            response.success = self.settings.checkpoint_file is not None
        except (OSError, ValueError) as err:
            response.success, response.message = False, f'could not write the checkpoint: {err}'
        return response
