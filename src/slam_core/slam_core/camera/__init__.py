"""The suite's camera model (``CameraModel``), its CameraInfo fields, ``lens``."""

from slam_core.camera.info import CameraInfoFields
from slam_core.camera.model import DISTORTION_MODELS, CameraModel

__all__ = ['DISTORTION_MODELS', 'CameraInfoFields', 'CameraModel']
