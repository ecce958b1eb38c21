"""slam_interfaces/PoseLink <-> the pose links of ``core.pose_links`` (ROS-free).

Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from monoslam_shadow_node.common.core.inputs import CameraPose
from slam_core.arrays import FloatArray
from slam_core.stamps import ns_to_stamp, stamp_to_ns

LINK_SUFFIX = '/link'
"""A pose topic's links are on the pose topic with this suffix."""
MAX_LINKS = 256
"""Links kept while waiting for their pose (about 8 s of a 30 Hz camera)."""


@dataclass(frozen=True, eq=False)
class PoseLinkInput:
    """One PoseLink: stamp (int ns), earlier stamps (K,), cross-covariances (K, 6, 6)."""

    stamp_ns: int
    earlier_stamps: tuple[int, ...]
    cross_covariances: FloatArray


def link_from_message(message: Any) -> PoseLinkInput:
    """Return what a PoseLink carries; ValueError naming the culprit."""
    stamp_ns = stamp_to_ns(message.header.stamp)
    earlier = tuple(stamp_to_ns(stamp) for stamp in message.earlier_stamps)
    cross = np.asarray(message.cross_covariances, dtype=np.float64)
    if cross.size != 36 * len(earlier) or not np.all(np.isfinite(cross)):
        raise ValueError(
            f'pose link at {stamp_ns} ns: cross_covariances holds {cross.size} values for '
            f'{len(earlier)} earlier stamps (36 finite numbers each)'
        )
    if any(stamp >= stamp_ns for stamp in earlier):
        raise ValueError(f'pose link at {stamp_ns} ns: an earlier_stamps entry is not earlier')
    return PoseLinkInput(stamp_ns, earlier, cross.reshape(-1, 6, 6))


def fill_pose_link(
    stamp_ns: int, earlier_stamps: tuple[int, ...], cross_covariances: ArrayLike,
    frame_id: str, message: Any, time_type: Callable[[], Any],
) -> Any:  # fmt: skip
    """Fill a slam_interfaces/PoseLink (stamps made by ``time_type``) and return it."""
    ns_to_stamp(stamp_ns, message.header.stamp)
    message.header.frame_id = frame_id
    message.earlier_stamps = [ns_to_stamp(stamp, time_type()) for stamp in earlier_stamps]
    message.cross_covariances = np.asarray(cross_covariances, dtype=np.float64).ravel().tolist()
    return message


class PoseLinks:
    """Pairs poses with their links, whichever comes first; counts links and poses by fate."""

    def __init__(self, capacity: int = MAX_LINKS) -> None:
        self._links: OrderedDict[int, PoseLinkInput] = OrderedDict()
        self._capacity = capacity
        self._waiting: CameraPose | None = None
        self.received = self.linked = self.unlinked = self.unused = 0
        self.rejected = 0  # counted by the caller, which reads the messages

    def on_pose(self, pose: CameraPose) -> list[CameraPose]:
        """Take a pose; return the poses ready to use, in order."""
        ready = self.flush()
        while self._links and next(iter(self._links)) < pose.stamp_ns:
            self._links.popitem(last=False)  # their poses have passed
            self.unused += 1
        link = self._links.pop(pose.stamp_ns, None)
        if link is not None or pose.covariance is None or not self.received:
            ready.append(self._with(pose, link))
        else:
            self._waiting = pose
        return ready

    def on_link(self, link: PoseLinkInput) -> list[CameraPose]:
        """Take a link; return the waiting pose it completes (or nothing)."""
        self.received += 1
        waiting = self._waiting
        if waiting is not None and waiting.stamp_ns == link.stamp_ns:
            self._waiting = None
            return [self._with(waiting, link)]
        self._links[link.stamp_ns] = link
        while len(self._links) > self._capacity:
            self._links.popitem(last=False)
            self.unused += 1
        return []

    def flush(self) -> list[CameraPose]:
        """Release the pose waiting for its link, without it (the inputs went quiet)."""
        waiting, self._waiting = self._waiting, None
        return [] if waiting is None else [self._with(waiting, None)]

    def _with(self, pose: CameraPose, link: PoseLinkInput | None) -> CameraPose:
        if link is None or pose.covariance is None:
            self.unlinked += 1
            return pose
        self.linked += 1
        return replace(
            pose, cross_stamps=link.earlier_stamps, cross_covariances=link.cross_covariances
        )
