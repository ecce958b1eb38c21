"""Score a graph's Shadow filter decisions on a TUM-layout sequence against labels from its
depth maps and motion capture: the tracks the graph's own feature tracker published
(``/features`` in the recording) are labelled moving or static by the rule
``tum_rgbd_sequence`` uses (``tum_labels.label_sequence``, 'masks'; the pose error measured
on the static opening), and each labelled track's first decision (``/shadow/tracks``,
``/shadow/static_features``; a revocation on ``/monoslam/revoked`` counts as DYNAMIC) and
last status are compared with its label (issue 43's acceptance: static called DYNAMIC at
most 10 % of the decided static tracks, moving called STATIC at most 2 % of the decided
moving ones).

Run (after ``slam_run monoslam_shadow_rgbd.yaml --bag out/bonn_crowd/bonn_crowd.mcap
--paced --processes --exit-when-player-done``; a few minutes: the masks)::

    source scripts/env.sh
    python bench/graph_classification.py --dataset ../shared/data/bonn_crowd \\
        --record out/monoslam_shadow_rgbd_record
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from monoslam_shadow_node.core.shadow_track import DYNAMIC, PENDING, STATIC
from slam_core.stamps import stamp_to_ns
from slam_evaluation.classification_figure import FEATURES_TOPIC, STATUS_TOPICS, _read
from slam_evaluation.tum_labels import label_sequence
from slam_evaluation.tum_sequence import ImportSettings, pose_rule
from slam_evaluation.tum_tracking import TrackedImages
from slam_sim.core.depth_labels import DepthSightings, frame_sightings
from slam_sim.core.rgbd_depth import read_depth_m
from slam_sim.core.tum_rgbd import read_tum_rgbd


def recorded_tracks(
    record: Path, stamps_ns: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[tuple[int, int, int]]]:
    """Return the recorded features as (image index, id, pixel) arrays, matched to the
    sequence's images by stamp, and the status events (stamp ns, id, status) in stamp
    order."""
    index_of = {int(s): k for k, s in enumerate(stamps_ns.tolist())}
    images, ids, pixels = [], [], []
    events: list[tuple[int, int, int]] = []
    unmatched = 0
    for topic, message in _read(record, [FEATURES_TOPIC, *STATUS_TOPICS], FEATURES_TOPIC):
        stamp = stamp_to_ns(message.header.stamp)
        if topic == FEATURES_TOPIC:
            image = index_of.get(stamp)
            if image is None:
                unmatched += 1
                continue
            for track in message.tracks:
                images.append(image)
                ids.append(int(track.id))
                pixels.append((float(track.u), float(track.v)))
        else:
            revoked = topic == '/monoslam/revoked'
            for track in message.tracks:
                events.append((stamp, int(track.id), DYNAMIC if revoked else int(track.status)))
    if unmatched:
        print(f'{unmatched} features messages match no image stamp (left out)')
    events.sort(key=lambda event: event[0])
    return (
        np.array(images, dtype=np.int64),
        np.array(ids, dtype=np.int64),
        np.array(pixels, dtype=np.float64).reshape(-1, 2),
        events,
    )


def score(moving_by_id: dict[int, bool], events: list[tuple[int, int, int]]) -> dict[str, Any]:
    """Return the decisions of the labelled tracks against their labels."""
    first: dict[int, int] = {}
    last: dict[int, int] = {}
    for _, track_id, status in events:
        if status in (STATIC, DYNAMIC):
            first.setdefault(track_id, status)
        if status in (PENDING, STATIC, DYNAMIC):
            last[track_id] = status
    out: dict[str, Any] = {}
    for name, book in (('first_decision', first), ('last_status', last)):
        counts = {}
        for label, moving in (('static', False), ('moving', True)):
            tracks = [i for i, m in moving_by_id.items() if m == moving]
            decided = [i for i in tracks if book.get(i) in (STATIC, DYNAMIC)]
            wrong = STATIC if moving else DYNAMIC
            called = sum(1 for i in decided if book[i] == wrong)
            counts[label] = {
                'tracks': len(tracks),
                'decided': len(decided),
                'called_' + ('static' if moving else 'dynamic'): called,
                'share': called / len(decided) if decided else None,
            }
        out[name] = counts
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--dataset', type=Path, required=True, help='TUM-layout sequence')
    parser.add_argument('--convention', default='bonn')
    parser.add_argument('--record', type=Path, required=True, help="the graph's recording")
    parser.add_argument('--out', type=Path, default=None, help='JSON of the figures')
    args = parser.parse_args(argv)
    sequence = read_tum_rgbd(args.dataset, convention=args.convention)
    settings = ImportSettings()
    rule, _ = pose_rule(sequence, settings)
    images, ids, pixels, events = recorded_tracks(args.record, sequence.stamps_ns)
    depth = []
    for image in np.unique(images).tolist():
        if not (sequence.has_pose[image] and sequence.depth_index[image] >= 0):
            continue
        depth_m = read_depth_m(
            sequence.depth.files[sequence.depth_index[image]], sequence.depth_units_per_m
        )
        here = images == image
        depth.append(
            frame_sightings(
                sequence.camera, (image, int(sequence.stamps_ns[image])), ids[here],
                pixels[here], depth_m, sequence.poses[image], rule,
            )
        )  # fmt: skip
    tracked = TrackedImages(images, ids, pixels, DepthSightings.concatenate(depth))
    labelled = label_sequence(
        sequence, tracked, rule=settings.label_rule, endpoint_rule=rule,
        static_images=settings.static_images,
    )  # fmt: skip
    labels = labelled.chosen.labels
    report = {'tracks': labels.counts(), **score(labels.moving_by_id(), events)}
    print(json.dumps(report, indent=1))
    if args.out is not None:
        args.out.write_text(json.dumps(report, indent=1) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
