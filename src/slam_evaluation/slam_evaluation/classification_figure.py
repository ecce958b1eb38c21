"""classification_figure: the Shadow filter's statuses over time drawn on the images.

Design notes: docs/design/evaluation.md"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from monoslam_shadow_node.common.core.feature_status import DYNAMIC
from monoslam_shadow_node.feature_tracker.overlay import StatusBook, draw_features
from slam_core.cli import console_main
from slam_core.files import write_atomically
from slam_core.stamps import stamp_to_ns
from slam_evaluation.tum_label_figure import tiled_png
from slam_ros.bag.source import BagSource

IMAGE_TOPIC = '/camera/image_raw/compressed'
FEATURES_TOPIC = '/features'
STATUS_TOPICS = ('/shadow/tracks', '/shadow/static_features', '/monoslam/revoked')


@dataclass(frozen=True, eq=False)
class StatusEvent:
    """Statuses heard at a header stamp (int ns): (id, status) pairs."""

    stamp_ns: int
    entries: tuple[tuple[int, int], ...]


def statuses_as_of(events: Sequence[StatusEvent], stamp_ns: int) -> StatusBook:
    """Return each id's latest status among ``events`` stamped up to ``stamp_ns`` (events in any
    order; at one stamp, in the order given)."""
    book = StatusBook()
    for event in sorted(
        (e for e in events if e.stamp_ns <= stamp_ns), key=lambda e: e.stamp_ns
    ):  # sorted is stable
        book.update(event.entries)
    return book


def nearest_stamps(stamps: Sequence[int], times_s: Iterable[float]) -> list[int]:
    """Return, per time (s after the first stamp), the nearest of ``stamps`` (int ns)."""
    ordered = np.array(sorted(stamps), dtype=np.int64)
    if not len(ordered):
        raise ValueError('no images')
    wanted = [ordered[0] + round(t * 1e9) for t in times_s]
    return [int(ordered[np.argmin(np.abs(ordered - w))]) for w in wanted]


def read_messages(path: Path, topics: Sequence[str], required: str) -> list[tuple[str, Any]]:
    """Return (topic, message) of ``topics`` in ``path`` in stamp order; ValueError when the
    bag lacks ``required``."""
    with BagSource(path) as bag:
        found = set(bag.topics())
        if required not in found:
            raise ValueError(f'{path}: no {required} (topics: {", ".join(sorted(found))})')
        return [
            (m.topic, bag.typestore.deserialize_cdr(m.data, m.msgtype))
            for m in bag.messages([t for t in topics if t in found])
        ]


def panels(bag: Path, record: Path, times_s: Sequence[float]) -> list[np.ndarray]:
    """Return one drawn image (BGR) per time: the nearest image, its features in their status."""
    images = {
        stamp_to_ns(m.header.stamp): m for _, m in read_messages(bag, [IMAGE_TOPIC], IMAGE_TOPIC)
    }
    recorded = read_messages(record, [FEATURES_TOPIC, *STATUS_TOPICS], FEATURES_TOPIC)
    features = {stamp_to_ns(m.header.stamp): m for t, m in recorded if t == FEATURES_TOPIC}
    events = []
    for topic, message in recorded:
        if topic in STATUS_TOPICS:
            dynamic = topic == '/monoslam/revoked'
            entries = tuple(
                (int(t.id), DYNAMIC if dynamic else int(t.status)) for t in message.tracks
            )
            events.append(StatusEvent(stamp_to_ns(message.header.stamp), entries))
    drawn = []
    for stamp in nearest_stamps(sorted(set(images) & set(features)), times_s):
        image = cv2.imdecode(np.frombuffer(bytes(images[stamp].data), np.uint8), cv2.IMREAD_COLOR)
        if image is None:
            raise ValueError(f'{bag}: the image at stamp {stamp} ns does not decode')
        tracks = features[stamp].tracks
        ids = np.array([t.id for t in tracks], dtype=np.int64)
        pixels = np.array([(t.u, t.v) for t in tracks], dtype=np.float64).reshape(-1, 2)
        canvas, _ = draw_features(image, ids, pixels, statuses_as_of(events, stamp))
        seconds = (stamp - min(images)) * 1e-9
        cv2.putText(canvas, f't = {seconds:.1f} s', (5, canvas.shape[0] - 8),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)  # fmt: skip
        drawn.append(canvas)
    return drawn


@console_main('classification_figure')
def main(argv: list[str] | None = None) -> int:
    """Command line (module docstring)."""
    parser = argparse.ArgumentParser(
        prog='classification_figure',
        description="the Shadow filter's classification over time, drawn on the images",
    )
    parser.add_argument('--bag', type=Path, required=True, help='the input bag (images)')
    parser.add_argument('--record', type=Path, required=True, help="the graph's recording")
    parser.add_argument('--times', default='3,9,15,21', help='s after the first image')
    parser.add_argument('--out', type=Path, default=Path('out/classification.png'))
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    try:
        times = [float(t) for t in args.times.split(',') if t.strip()]
        drawn = panels(args.bag, args.record, times)
        png = tiled_png(drawn)
    except ValueError as error:
        print(f'classification_figure: error: {error}', file=sys.stderr)  # noqa: T201
        return 2
    write_atomically(args.out, png)
    print(f'wrote {args.out}: {len(drawn)} images at {times} s')  # noqa: T201
    return 0
