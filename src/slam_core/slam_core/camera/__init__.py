"""The suite's one camera model: pinhole with plumb_bob or rational_polynomial distortion
(``model.CameraModel``), its CameraInfo fields (``info.CameraInfoFields``) and the lens
functions behind it (``lens``)."""

from slam_core.camera.info import CameraInfoFields
from slam_core.camera.model import DISTORTION_MODELS, CameraModel

__all__ = ['DISTORTION_MODELS', 'CameraInfoFields', 'CameraModel']
