"""``tf_tree``: parents, second parents and lookups through the tree, as tf2 would see them."""

from __future__ import annotations

from geometry_msgs.msg import TransformStamped
from tf2_msgs.msg import TFMessage

from slam_core.stamps import ns_to_stamp
from slam_ros.tf_tree import TfTree

S = 1_000_000_000


def message(*links: tuple[str, str, int]) -> TFMessage:
    """A TFMessage of (parent, child, stamp ns) links."""
    transforms = []
    for parent, child, stamp_ns in links:
        transform = TransformStamped()
        transform.header.frame_id = parent
        ns_to_stamp(stamp_ns, transform.header.stamp)
        transform.child_frame_id = child
        transform.transform.rotation.w = 1.0
        transforms.append(transform)
    return TFMessage(transforms=transforms)


def robot_tree() -> TfTree:
    """map -> odom (1 Hz) -> base_link (10 Hz) -> camera_link -> camera_optical_frame."""
    tree = TfTree()
    tree.add(
        message(('base_link', 'camera_link', 0), ('camera_link', 'camera_optical_frame', 0)),
        static=True,
    )
    for k in range(31):
        tree.add(message(('odom', 'base_link', k * S // 10)), static=False)
    for k in range(4):
        tree.add(message(('map', 'odom', k * S)), static=False)
    return tree


def test_a_chain_joins_frames_through_their_common_ancestor() -> None:
    tree = robot_tree()
    assert tree.lookup_chain('map', 'camera_optical_frame') == [
        'camera_optical_frame', 'camera_link', 'base_link', 'odom', 'map',
    ]  # fmt: skip
    assert tree.lookup_chain('camera_link', 'odom') == ['odom', 'base_link', 'camera_link']
    assert tree.lookup_chain('monoslam_map', 'map') is None
    assert not tree.conflicts and tree.transforms == 2 + 31 + 4


def test_a_lookup_needs_every_moving_link_on_both_sides_of_the_time() -> None:
    tree = robot_tree()
    assert tree.resolves('map', 'camera_optical_frame', 2 * S + S // 2)
    assert tree.resolves('map', 'camera_optical_frame', 3 * S)  # the last stamps, exactly
    assert not tree.resolves('map', 'camera_optical_frame', 3 * S + 1)  # extrapolation
    assert not tree.resolves('map', 'camera_optical_frame', -1)
    # odom -> camera does not go through map -> odom: its stamps do not matter
    assert tree.resolves('odom', 'camera_optical_frame', 3 * S)
    assert tree.resolves('base_link', 'camera_optical_frame', 100 * S)  # static only


def test_a_second_parent_is_reported_with_both_parents_and_their_topics() -> None:
    tree = robot_tree()
    tree.add(message(('map', 'camera_optical_frame', 3 * S)), static=False)
    tree.add(message(('odom', 'base_link', 4 * S)), static=False)  # the same parent: fine
    assert tree.conflicts == [
        "'camera_optical_frame' has parent 'camera_link' (/tf_static) and 'map' (/tf)"
    ]
    # the first parent stays: the tree is the one the robot publishes
    assert tree.lookup_chain('map', 'camera_optical_frame')[:2] == [
        'camera_optical_frame', 'camera_link',
    ]  # fmt: skip
