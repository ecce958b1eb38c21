"""Score a graph's Shadow filter decisions on a TUM-layout sequence against labels from its
depth maps and motion capture: the tracks the graph's own feature tracker published
(``/features`` in the recording) are labelled moving or static by the rule
``tum_rgbd_sequence`` uses (``tum_labels.label_sequence``, 'masks'; the pose error measured
on the static opening), and each labelled track's first decision (``/shadow/tracks``,
``/shadow/static_features``; a revocation on ``/monoslam/revoked`` counts as DYNAMIC) and
last status are compared with its label (issue 43's acceptance: static called DYNAMIC at
most 10 % of the decided static tracks, moving called STATIC at most 2 % of the decided
moving ones). When the recording has monoslam's ``/features/predicted``, it also counts,
per moving track, the images in which SLAM predicted it in view (a feature of its map) and
the tracker published it: an upper bound of the images SLAM measured it in (the gate may
refuse some; features on probation are measured with consider updates), against the bound
of 15, and the same from each track's first STATIC status on (cleared: before it, with
``undecided_probation``, SLAM only gives it consider updates, which never move the camera).

Run (after ``slam_run monoslam_shadow_rgbd.yaml --bag out/bonn_crowd/bonn_crowd.mcap
--paced --processes --exit-when-player-done``; a few minutes: the masks)::

    source scripts/env.sh
    python bench/graph_classification.py --dataset ../shared/data/bonn_crowd \\
        --record out/monoslam_shadow_rgbd_record
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from monoslam_shadow_node.common.core.feature_status import DYNAMIC, PENDING, STATIC
from slam_core.stamps import stamp_to_ns
from slam_evaluation.classification_figure import FEATURES_TOPIC, STATUS_TOPICS, read_messages
from slam_evaluation.tum_labels import label_sequence
from slam_evaluation.tum_sequence import ImportSettings, pose_rule
from slam_evaluation.tum_tracking import recorded_features, track_images
from slam_sim.core.tum_rgbd import read_tum_rgbd

PREDICTIONS_TOPIC = '/features/predicted'
BIN_S = 3.0
"""Width of the time bins of ``decisions_over_time``, s."""
MAX_MOVING_FRAMES = 15
"""Issue 43: no feature labelled moving is measured by SLAM in more than this many images."""


def recorded_statuses(
    record: Path, stamps_ns: np.ndarray
) -> tuple[list[tuple[int, int, int]], dict[int, set[int]]]:
    """Return the status events (stamp ns, id, status) in stamp order and, per image index
    (matched by stamp), the ids SLAM predicted in view for it."""
    index_of = {int(s): k for k, s in enumerate(stamps_ns.tolist())}
    events: list[tuple[int, int, int]] = []
    predicted: dict[int, set[int]] = {}
    for topic, message in read_messages(
        record, [*STATUS_TOPICS, PREDICTIONS_TOPIC], FEATURES_TOPIC
    ):
        stamp = stamp_to_ns(message.header.stamp)
        if topic == PREDICTIONS_TOPIC:
            image = index_of.get(stamp)
            if image is not None:  # in view: a search region (covariance) was sent
                in_view = {int(t.id) for t in message.tracks if float(t.covariance[0]) > 0.0}
                predicted.setdefault(image, set()).update(in_view)
        else:
            revoked = topic == '/monoslam/revoked'
            for track in message.tracks:
                events.append((stamp, int(track.id), DYNAMIC if revoked else int(track.status)))
    events.sort(key=lambda event: event[0])
    return events, predicted


def moving_in_map(
    moving_by_id: dict[int, bool],
    images: np.ndarray,
    ids: np.ndarray,
    predicted: dict[int, set[int]],
    cleared_from: dict[int, int] | None = None,
) -> dict[str, Any]:
    """Return, over the moving tracks, the images each was both published by the tracker and
    predicted in view by SLAM (module docstring): how many exceed ``MAX_MOVING_FRAMES`` and
    the most; with ``cleared_from`` (id -> index of the first image stamped at or after its
    first STATIC status), the same over the images from its clearance on (before it, a
    feature of SLAM's map is on probation with ``undecided_probation``: consider updates,
    which never move the camera)."""
    frames: dict[int, int] = {}
    cleared: dict[int, int] = {}
    for image, track_id in zip(images.tolist(), ids.tolist(), strict=True):
        if moving_by_id.get(track_id) and track_id in predicted.get(image, ()):
            frames[track_id] = frames.get(track_id, 0) + 1
            if cleared_from is not None and image >= cleared_from.get(track_id, len(images) + 1):
                cleared[track_id] = cleared.get(track_id, 0) + 1
    over = sorted(n for n in frames.values() if n > MAX_MOVING_FRAMES)
    report: dict[str, Any] = {
        'moving_tracks_in_map': len(frames),
        'over_bound': len(over),
        'bound_frames': MAX_MOVING_FRAMES,
        'most_frames': max(frames.values(), default=0),
    }
    if cleared_from is not None:
        report['moving_tracks_cleared_in_map'] = len(cleared)
        report['over_bound_cleared'] = sum(1 for n in cleared.values() if n > MAX_MOVING_FRAMES)
        report['most_frames_cleared'] = max(cleared.values(), default=0)
    return report


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


def decisions_over_time(
    moving_by_id: dict[int, bool], events: list[tuple[int, int, int]], start_ns: int
) -> dict[str, Any]:
    """Return the first decisions on the static tracks per ``BIN_S`` seconds from
    ``start_ns``: how many were STATIC and how many DYNAMIC (false alarms cluster where
    SLAM's pose is wrong)."""
    first: dict[int, tuple[int, int]] = {}
    for stamp, track_id, status in events:
        if status in (STATIC, DYNAMIC) and track_id not in first:
            first[track_id] = (stamp, status)
    bins: dict[str, dict[str, int]] = {}
    for track_id, (stamp, status) in first.items():
        if moving_by_id.get(track_id) is not False:
            continue
        start = BIN_S * math.floor((stamp - start_ns) * 1e-9 / BIN_S)
        counts = bins.setdefault(f'{start:g}-{start + BIN_S:g} s', {'STATIC': 0, 'DYNAMIC': 0})
        counts['STATIC' if status == STATIC else 'DYNAMIC'] += 1
    return dict(sorted(bins.items(), key=lambda item: float(item[0].split('-')[0])))


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
    features = recorded_features(args.record)
    unmatched = len(set(features) - set(sequence.stamps_ns.tolist()))
    if unmatched:
        print(f'{unmatched} features messages match no image stamp (left out)')
    tracked = track_images(sequence, rule, recorded=features)
    events, predicted = recorded_statuses(args.record, sequence.stamps_ns)
    labelled = label_sequence(
        sequence, tracked, rule=settings.label_rule, endpoint_rule=rule,
        static_images=settings.static_images,
    )  # fmt: skip
    labels = labelled.chosen.labels
    moving = labels.moving_by_id()
    report: dict[str, Any] = {'tracks': labels.counts(), **score(moving, events)}
    report['static_first_decisions_over_time'] = decisions_over_time(
        moving, events, int(sequence.stamps_ns[0])
    )
    if predicted:
        cleared_from: dict[int, int] = {}  # the first image from each first STATIC status on
        for stamp, track_id, status in events:
            if status == STATIC and track_id not in cleared_from:
                cleared_from[track_id] = int(np.searchsorted(sequence.stamps_ns, stamp))
        report['moving_in_slam_map'] = moving_in_map(
            moving, tracked.images, tracked.ids, predicted, cleared_from
        )
    else:
        print(f"{args.record}: no {PREDICTIONS_TOPIC}: SLAM's map is not scored")
    print(json.dumps(report, indent=1))
    if args.out is not None:
        args.out.write_text(json.dumps(report, indent=1) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
