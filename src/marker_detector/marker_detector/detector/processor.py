"""The marker_detector's ROS-free processor: camera model, extrinsics and per-image detection.
Per image: detections (camera optical frame), rejections and range-bearing observations (base
frame); an unusable input raises ``InputError`` with the reason. The camera mount comes from
/tf_static or from parameters. Design notes: docs/design/marker_core.md"""

from __future__ import annotations

import numpy as np

from marker_detector.core.base_frame import to_range_bearing
from marker_detector.core.detection import (
    DetectionResult,
    detect_markers,
    make_detector,
)
from marker_detector.core.detector_config import DetectorConfig
from marker_detector.core.frame_types import (
    ExtrinsicsConfig,
    FrameOutput,
    InputError,
    StaticTransforms,
)
from marker_detector.core.roi import SearchPlan
from slam_core.camera import CameraModel
from slam_core.geometry.se3 import optical_from_link, transform_from_xyz_rpy


class MarkerProcessor:
    """Camera model, extrinsics and detector settings; turns images into FrameOutputs."""

    def __init__(
        self,
        config: DetectorConfig,
        extrinsics: ExtrinsicsConfig,
        search: SearchPlan | None = None,
    ) -> None:
        self.config = config
        self.extrinsics = extrinsics
        self.search = search if search is not None else SearchPlan()
        self.detector = make_detector(config)
        self.camera: CameraModel | None = None
        self.camera_frame = ''
        self.camera_info_error: str | None = None  # why the last camera_info was rejected
        self.transforms = StaticTransforms()
        self._fixed_extrinsics: np.ndarray | None = None
        if extrinsics.source == 'parameters':
            self._fixed_extrinsics = (
                transform_from_xyz_rpy(extrinsics.camera_xyz_m, extrinsics.camera_rpy_rad)
                @ optical_from_link()
            )

    def reconfigure(self, config: DetectorConfig) -> None:
        """Use new detector settings from the next image on."""
        self.detector = make_detector(config)
        self.config = config

    def set_camera_info(
        self,
        frame_id: str,
        width: int,
        height: int,
        k: list[float],
        d: list[float],
        distortion_model: str,
    ) -> None:
        """Take a camera_info; raise InputError naming the field when it is unusable."""
        try:
            camera = CameraModel.from_camera_info(width, height, k, d, distortion_model)
        except ValueError as err:
            self.camera_info_error = f'camera_info (frame {frame_id!r}) rejected: {err}'
            raise InputError(self.camera_info_error) from None
        self.camera_info_error = None
        if self.camera is not None and camera != self.camera:
            self.search.reset()
        self.camera = camera
        self.camera_frame = frame_id

    def no_camera_reason(self) -> str:
        """Why there is no camera model: the last camera_info's rejection, or that none came."""
        if self.camera_info_error is not None:
            return (
                f'no usable camera_info: {self.camera_info_error}; fix the calibration the '
                'camera driver publishes'
            )
        return 'no camera_info received yet; is camera/camera_info published?'

    def image_frame(self, frame_id: str) -> str:
        """An image's camera frame: its header's, or the camera_info's when it has none."""
        return frame_id or self.camera_frame

    def base_from_camera(self, camera_frame: str) -> np.ndarray:
        """T_base_camera (4x4) of the image's frame; raise InputError when unknown."""
        if self._fixed_extrinsics is not None:
            return self._fixed_extrinsics
        transform = self.transforms.lookup(self.extrinsics.base_frame, camera_frame)
        if transform is None:
            known = ', '.join(sorted(self.transforms.parents)) or 'none yet'
            raise InputError(
                f'no static transform from {self.extrinsics.base_frame!r} to the camera frame '
                f'{camera_frame!r} (frames on /tf_static: {known}); set extrinsics_source to '
                "'parameters' or publish the camera mount on /tf_static"
            )
        return transform

    def process(self, stamp_ns: int, frame_id: str, image: np.ndarray) -> FrameOutput:
        """Detect markers in ``image`` (gray or BGR) taken at ``stamp_ns`` in ``frame_id``."""
        if self.camera is None:
            raise InputError(self.no_camera_reason())
        camera_frame = self.image_frame(frame_id)
        base_from_camera = self.base_from_camera(camera_frame)
        try:
            result = self._detect(stamp_ns, image, self.camera)
        except ValueError as err:
            raise InputError(f'image at {stamp_ns} ns: {err}') from None
        observations = [to_range_bearing(d, base_from_camera) for d in result.detections]
        return FrameOutput(
            stamp_ns=stamp_ns,
            camera_frame=camera_frame,
            base_frame=self.extrinsics.base_frame,
            detections=list(result.detections),
            rejections=list(result.rejections),
            observations=observations,
        )

    def _detect(self, stamp_ns: int, image: np.ndarray, camera: CameraModel) -> DetectionResult:
        """Detect in the search plan's boxes, or in the whole image (``core.roi``)."""
        boxes = self.search.boxes(stamp_ns, image.shape)
        result = detect_markers(image, camera, self.config, self.detector, boxes)
        full = boxes is None
        if not full and self.search.needs_full_search({d.id for d in result.detections}):
            result = detect_markers(image, camera, self.config, self.detector)
            full = True
        self.search.searched(full, {d.id: d.corners_px for d in result.detections})
        return result
