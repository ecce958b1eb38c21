"""Moving/static labels of the tracks of a TUM-layout sequence (``LABEL_RULES``).

Design notes: docs/design/evaluation.md"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from slam_core.arrays import FloatArray
from slam_evaluation.tum_label_figure import LabelledImage, MaskedImage, labels_png, masks_png
from slam_evaluation.tum_tracking import TrackedImages
from slam_sim.core.depth_labels import LabelRule, TrackLabels, label_tracks
from slam_sim.core.label_gate import DepthMm, depth_to_mm
from slam_sim.core.mask_labels import (
    MaskLabelRule,
    TrackSightings,
    label_by_masks,
    mask_sightings,
)
from slam_sim.core.motion_masks import CodeArray, MaskedFrame, MaskRule, sequence_masks
from slam_sim.core.tum_rgbd import TumRgbd

LABEL_RULES = ('masks', 'endpoints')


@dataclass(frozen=True, eq=False)
class RuleLabels:
    """One rule's labels: all tracks and the static opening's."""

    labels: TrackLabels
    opening: TrackLabels

    def summary(self) -> dict[str, object]:
        """Return the counts and the static opening's false-alarm rate for a report."""
        return {
            'tracks': self.labels.counts(),
            'static_opening': self.opening.counts(),
            'false_alarm_rate': self.opening.moving_share(),
        }


@dataclass(frozen=True, eq=False)
class SequenceLabels:
    """The labels by rule name, the chosen rule, the kept masks (image -> (H, W)), gate masks."""

    rule: str
    by_rule: dict[str, RuleLabels]
    masks: dict[int, CodeArray] = field(default_factory=dict)
    gate_masks: dict[int, GateMask] = field(default_factory=dict)
    """With the mask rule: per colour image with a mask, what ``label_gate`` reads (GateMask)."""

    @property
    def chosen(self) -> RuleLabels:
        """The chosen rule's labels."""
        return self.by_rule[self.rule]


def mask_images(sequence: TumRgbd, images: tuple[int, ...]) -> dict[int, int]:
    """Return figure image -> the nearest colour image with a depth map and a pose."""
    masked = np.flatnonzero((sequence.depth_index >= 0) & sequence.has_pose)
    if not len(masked):
        return {}
    return {image: int(masked[np.argmin(np.abs(masked - image))]) for image in images}


def mask_rules(endpoint_rule: LabelRule) -> tuple[MaskRule, MaskLabelRule]:
    """Return the mask rule's settings."""
    error, sigma_px = endpoint_rule.pose_error, endpoint_rule.pixel_sigma_px
    return (
        MaskRule(pose_error=error, pixel_sigma_px=sigma_px),
        MaskLabelRule(pose_error=error, pixel_sigma_px=sigma_px),
    )


def label_sequence(
    sequence: TumRgbd,
    tracked: TrackedImages,
    *,
    rule: str,
    endpoint_rule: LabelRule,
    static_images: int,
    keep_masks: tuple[int, ...] = (),
    progress: Callable[[int], None] | None = None,
) -> SequenceLabels:
    """Return the labels of the posed images' tracks; ValueError for an unknown ``rule``."""
    if rule not in LABEL_RULES:
        raise ValueError(f'label rule {rule!r}: use one of {", ".join(LABEL_RULES)}')
    posed = sequence.has_pose[tracked.images]
    ids, images = tracked.ids[posed], tracked.images[posed]
    opening_ids = ids[images < static_images]
    depth = tracked.depth
    by_rule = {
        'endpoints': RuleLabels(
            label_tracks(ids, depth, endpoint_rule),
            label_tracks(opening_ids, depth.select(depth.frames < static_images), endpoint_rule),
        )
    }
    masks: dict[int, CodeArray] = {}
    gate: dict[int, GateMask] = {}
    if rule == 'masks':
        mask_rule, label_rule = mask_rules(endpoint_rule)
        frames = _keeping(sequence_masks(sequence, mask_rule), keep_masks, masks, progress)
        tracks = TrackSightings.of(tracked.images, tracked.ids, tracked.pixels)

        def coded(frame: MaskedFrame, codes: CodeArray) -> None:
            gate[frame.image] = GateMask(codes, depth_to_mm(frame.depth_m), frame.pose)

        sightings = mask_sightings(sequence.camera, tracks, frames, label_rule, coded)
        in_opening = sightings.images < static_images
        depth_only = sightings.depth_only()
        by_rule['masks'] = RuleLabels(
            label_by_masks(ids, sightings, label_rule),
            label_by_masks(opening_ids, sightings.select(in_opening), label_rule),
        )
        by_rule['masks_depth_only'] = RuleLabels(
            label_by_masks(ids, depth_only, label_rule),
            label_by_masks(opening_ids, depth_only.select(in_opening), label_rule),
        )
    return SequenceLabels(rule, by_rule, masks, gate)


def _keeping(
    frames: Iterator[MaskedFrame],
    keep: tuple[int, ...],
    kept: dict[int, CodeArray],
    progress: Callable[[int], None] | None,
) -> Iterator[MaskedFrame]:
    """Yield ``frames``, keeping the masks of ``keep``; ``progress(frames done)``."""
    for done, frame in enumerate(frames, start=1):
        if frame.image in keep:
            kept[frame.image] = frame.mask
        if progress is not None:
            progress(done)
        yield frame


@dataclass(frozen=True, eq=False)
class GateMask:
    """What ``slam_sim.core.label_gate`` takes of one mask: the pixel codes (H, W), the depth
    map (H, W) mm and the pose (4, 4)."""

    codes: CodeArray
    depth_mm: DepthMm
    pose: FloatArray


def rule_report(name: str, endpoint_rule: LabelRule) -> dict[str, Any]:
    """Return the label rules' settings for the report."""
    report: dict[str, Any] = {
        'name': name,
        'pose_error': asdict(endpoint_rule.pose_error),
        'endpoints': {**asdict(endpoint_rule), 'chi2_bound': endpoint_rule.bound},
    }
    if name == 'masks':
        mask_rule, track_rule = mask_rules(endpoint_rule)
        report['masks'] = {
            'mask': {k: v for k, v in asdict(mask_rule).items() if k != 'pose_error'},
            'tracks': {k: v for k, v in asdict(track_rule).items() if k != 'pose_error'},
            'motion_chi2_bound': track_rule.bound,
        }
    return report


def label_figures(
    sequence: TumRgbd, tracked: TrackedImages, labelled: SequenceLabels, images: tuple[int, ...]
) -> dict[str, bytes]:
    """Return labels.png and masks.png (name -> PNG bytes) of the figure images."""
    labels = labelled.chosen.labels
    drawn = [i for i in images if i in tracked.kept and sequence.has_pose[i]]
    items = []
    for index in drawn:
        here = tracked.images == index
        pixels, codes = tracked.pixels[here], labels.label_of(tracked.ids[here])
        items.append(LabelledImage(index, tracked.kept[index], pixels, codes))
    figures = {'labels.png': labels_png(items)} if items else {}
    mask_of = mask_images(sequence, tuple(drawn))
    masked = [
        MaskedImage(i, mask_of[i], tracked.kept[mask_of[i]], labelled.masks[mask_of[i]])
        for i in drawn
        if mask_of.get(i) in labelled.masks and mask_of[i] in tracked.kept
    ]
    if masked:
        figures['masks.png'] = masks_png(masked)
    return figures
