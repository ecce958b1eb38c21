"""Texture, antialiasing and sensor settings of the dynamic scene's renderer."""

from __future__ import annotations

from dataclasses import dataclass, field

from slam_sim.core.camera_effects import ImageEffects

ATLAS_ALIGN = 16
"""Texture charts' sizes and atlas offsets are multiples of this (2 ** (most mip levels - 1))."""


def _mild_effects() -> ImageEffects:
    return ImageEffects(
        gain_drift=(0.0, 0.0), gain_jitter=0.0, offset_drift=0.0, vignetting=0.1,
        defocus_sigma_px=(0.0, 0.0), exposure_s=0.0, read_noise=1.2, shot_noise=0.06,
    )  # fmt: skip


@dataclass(frozen=True)
class RenderOptions:
    """Texture, antialiasing and sensor settings of the renderer (sizes in m, texels)."""

    texels_per_m: float = 100.0
    patches_per_m2: float = 20.0
    patch_size_m: tuple[float, float] = (0.05, 0.25)
    object_cell_m: float = 0.08
    object_face_texels: int = 96
    supersample: int = 3
    mip_levels: int = 5
    lod_bias: float = -1.0
    effects: ImageEffects | None = field(default_factory=_mild_effects)

    def __post_init__(self) -> None:
        """Reject settings that cannot be rendered; the message names the field."""
        if not 10.0 <= self.texels_per_m <= 400.0:
            raise ValueError(f'texels_per_m = {self.texels_per_m} must be in [10, 400]')
        if not 0.0 <= self.patches_per_m2 <= 400.0:
            raise ValueError(f'patches_per_m2 = {self.patches_per_m2} must be in [0, 400]')
        low, high = self.patch_size_m
        if not 0.0 < low <= high <= 2.0:
            raise ValueError(f'patch_size_m = {self.patch_size_m} must be 0 < min <= max <= 2')
        if not 0.01 <= self.object_cell_m <= 1.0:
            raise ValueError(f'object_cell_m = {self.object_cell_m} must be in [0.01, 1]')
        if not 16 <= self.object_face_texels <= 512 or self.object_face_texels % ATLAS_ALIGN:
            raise ValueError(
                f'object_face_texels = {self.object_face_texels} must be a multiple of 16 '
                'in [16, 512]'
            )
        if not 1 <= self.supersample <= 8:
            raise ValueError(f'supersample = {self.supersample} must be in [1, 8]')
        if not 1 <= self.mip_levels <= 5:
            raise ValueError(f'mip_levels = {self.mip_levels} must be in [1, 5]')
