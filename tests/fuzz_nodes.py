"""Fuzzing every node input: messages built from the ROS message definitions, sane or with
extreme field values, fed to the subscription callbacks of real nodes (no DDS).

One ``FuzzTarget`` per (node, input topic). A node is made once per target and primed with
one sane message on each input; every example then feeds one message to the input under
test (a sane message of the type with up to four fields replaced by extreme values: NaN,
inf, huge, negative, empty or long sequences, wrong encodings and frames; or a message with
every field random), then one sane message on each other input (later stamps), then runs
the node's timers. ``feed`` reports what a node must never do with such input:

- an exception escaping a callback (the executor would end the node);
- NaN or inf in a published message (``/diagnostics`` is text);
- an error logged (or a warning that something was dropped, refused or rejected) without
  any count of the node's ``_counts`` changing: a rejection must be counted.

``SLAM_FUZZ_EXAMPLES`` sets the examples per target (``examples()``); the tests use a small
number, ``bench/fuzz_inputs.py`` 10,000.
"""

from __future__ import annotations

import importlib
import math
import os
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from hypothesis import strategies as st
from rclpy.node import Node
from rclpy.serialization import serialize_message

DEFAULT_EXAMPLES = 25
"""Examples per input in the test suite: the 17 inputs together in well under a minute."""

WIDTH, HEIGHT = 64, 48
FRAMES = ('camera_optical_frame', 'base_link', 'odom', 'map', 'camera_link', '', 'x' * 300)
STRINGS = (
    *FRAMES,
    'mono8', '8UC1', 'bgr8', 'rgb8', 'bgra8', 'rgba8', '16UC1', 'yuv422', 'jpeg', 'png',
    'plumb_bob', 'rational_polynomial', 'equidistant', 'DICT_APRILTAG_36h11', 'tag36h11',
    'DICT_4X4_50', '\x00', 'é',
)  # fmt: skip
EXTREME_FLOATS = (
    math.nan, math.inf, -math.inf, 0.0, -0.0, 1e308, -1e308, 1e-308, 5e-324, 1e30, -1e30,
    1.0, -1.0, 1e-9,
)  # fmt: skip
INT_BOUNDS = {
    'int8': (-(2**7), 2**7 - 1), 'uint8': (0, 2**8 - 1), 'octet': (0, 2**8 - 1),
    'int16': (-(2**15), 2**15 - 1), 'uint16': (0, 2**16 - 1),
    'int32': (-(2**31), 2**31 - 1), 'uint32': (0, 2**32 - 1),
    'int64': (-(2**63), 2**63 - 1), 'uint64': (0, 2**64 - 1), 'char': (0, 255),
}  # fmt: skip


def examples() -> int:
    """Examples per input: ``SLAM_FUZZ_EXAMPLES`` or ``DEFAULT_EXAMPLES``."""
    return int(os.environ.get('SLAM_FUZZ_EXAMPLES', DEFAULT_EXAMPLES))


# --- message types -------------------------------------------------------------------------


def message_class(name: str) -> type:
    """'std_msgs/Header' -> the class."""
    package, _, type_name = name.partition('/')
    return getattr(importlib.import_module(f'{package}.msg'), type_name.split('/')[-1])


def split_type(text: str) -> tuple[str, str, int | None]:
    """A field type -> (kind 'one', 'seq' or 'array', element type, size)."""
    if text.startswith('sequence<'):
        inner = text[len('sequence<') : -1]
        element, _, bound = inner.partition(', ')
        return 'seq', element, int(bound) if bound else None
    if text.endswith(']') and '[' in text:
        element, _, size = text[:-1].partition('[')
        return 'array', element, int(size)
    if text.startswith(('string<', 'wstring')):
        return 'one', 'string', None
    return 'one', text, None


# --- values ----------------------------------------------------------------------------------


def float_values(element: str, extreme: bool) -> st.SearchStrategy[float]:
    if not extreme:
        return st.floats(-10.0, 10.0)
    width = 32 if element == 'float' else 64
    return st.one_of(
        st.sampled_from(EXTREME_FLOATS[3:] if width == 32 else EXTREME_FLOATS)
        | st.sampled_from(EXTREME_FLOATS[:3]),
        st.floats(allow_nan=True, allow_infinity=True, width=width),
    )


def scalar_values(element: str, extreme: bool) -> st.SearchStrategy[Any]:
    if element in ('double', 'float'):
        return float_values(element, extreme)
    if element in INT_BOUNDS:
        low, high = INT_BOUNDS[element]
        if not extreme:
            return st.integers(max(low, 0), min(high, 100))
        return st.sampled_from((low, high, 0, 1, low + 1, high - 1)) | st.integers(low, high)
    if element == 'boolean':
        return st.booleans()
    if element in ('string', 'wstring'):
        return st.sampled_from(STRINGS) | (st.text(max_size=12) if extreme else st.nothing())
    raise ValueError(f'no values for {element}')


def sane_scalar(rng: np.random.Generator, element: str) -> Any:
    """A small value of a basic type (a string from STRINGS' frames and codecs)."""
    if element in ('double', 'float'):
        return float(rng.uniform(-10.0, 10.0))
    if element in INT_BOUNDS:
        return int(rng.integers(0, 101))
    if element == 'boolean':
        return bool(rng.integers(0, 2))
    return str(STRINGS[int(rng.integers(0, len(STRINGS)))])


def quaternion(rng: np.random.Generator) -> tuple[float, float, float, float]:
    values = rng.uniform(-1.0, 1.0, 4) + np.array([0.0, 0.0, 0.0, 1e-3])
    x, y, z, w = values / np.linalg.norm(values)
    return float(x), float(y), float(z), float(w)


def sane(rng: np.random.Generator, type_name: str) -> Any:
    """A well-formed message of ``type_name`` (small finite numbers, unit quaternions,
    consistent images and camera_info), from a numpy generator (fast: hypothesis draws
    only the extreme values)."""
    cls = message_class(type_name)
    special = SANE_BUILDERS.get(type_name)
    if special is not None:
        return special(rng)
    message = cls()
    for name, text in cls.get_fields_and_field_types().items():
        kind, element, size = split_type(text)
        if kind == 'one' and '/' in element:
            value = sane(rng, element)
        elif kind == 'one':
            value = sane_scalar(rng, element)
        else:
            count = size if kind == 'array' else int(rng.integers(0, min(size or 4, 4) + 1))
            assert count is not None
            if '/' in element:
                value = [sane(rng, element) for _ in range(count)]
            elif element in ('uint8', 'octet'):
                value = rng.integers(0, 101, count).astype(np.uint8).tobytes()
            else:
                value = [sane_scalar(rng, element) for _ in range(count)]
        setattr(message, name, value)
    return message


def _quaternion_message(rng: np.random.Generator) -> Any:
    q = message_class('geometry_msgs/Quaternion')()
    q.x, q.y, q.z, q.w = quaternion(rng)
    return q


def _camera_info(rng: np.random.Generator) -> Any:
    info = message_class('sensor_msgs/CameraInfo')()
    info.header.frame_id = 'camera_optical_frame'
    info.width, info.height = WIDTH, HEIGHT
    fx = float(rng.uniform(40.0, 80.0))
    info.k = [fx, 0.0, WIDTH / 2, 0.0, fx, HEIGHT / 2, 0.0, 0.0, 1.0]
    info.p = [fx, 0.0, WIDTH / 2, 0.0, 0.0, fx, HEIGHT / 2, 0.0, 0.0, 0.0, 1.0, 0.0]
    info.d = [0.0] * 5
    info.distortion_model = 'plumb_bob'
    return info


def _pixels(rng: np.random.Generator) -> np.ndarray:
    image = rng.integers(0, 256, (HEIGHT, WIDTH), dtype=np.uint8)
    return np.asarray(cv2.GaussianBlur(image, (5, 5), 1.0))


def _image(rng: np.random.Generator) -> Any:
    encoding = ('mono8', 'bgr8', 'rgba8')[int(rng.integers(0, 3))]
    pixels = _pixels(rng)
    if encoding != 'mono8':
        code = cv2.COLOR_GRAY2BGR if encoding == 'bgr8' else cv2.COLOR_GRAY2RGBA
        pixels = cv2.cvtColor(pixels, code)
    message = message_class('sensor_msgs/Image')()
    message.header.frame_id = 'camera_optical_frame'
    message.height, message.width = HEIGHT, WIDTH
    message.encoding, message.step = encoding, pixels.strides[0]
    message.data = pixels.tobytes()
    return message


def _compressed(rng: np.random.Generator) -> Any:
    codec = ('png', 'jpeg')[int(rng.integers(0, 2))]
    ok, encoded = cv2.imencode('.png' if codec == 'png' else '.jpg', _pixels(rng))
    assert ok
    message = message_class('sensor_msgs/CompressedImage')()
    message.header.frame_id = 'camera_optical_frame'
    message.format, message.data = codec, encoded.tobytes()
    return message


def _pose_link(rng: np.random.Generator) -> Any:
    """A link to 1-3 earlier poses (stamps near 0, before any the feeder gives) with small
    cross-covariances, 36 per stamp."""
    message = message_class('slam_interfaces/PoseLink')()
    time = message_class('builtin_interfaces/Time')
    count = int(rng.integers(1, 4))
    message.earlier_stamps = [time(sec=0, nanosec=k + 1) for k in range(count)]
    message.cross_covariances = (1e-4 * rng.standard_normal(36 * count)).tolist()
    return message


SANE_BUILDERS: dict[str, Callable[[np.random.Generator], Any]] = {
    'slam_interfaces/PoseLink': _pose_link,
    'geometry_msgs/Quaternion': _quaternion_message,
    'sensor_msgs/CameraInfo': _camera_info,
    'sensor_msgs/Image': _image,
    'sensor_msgs/CompressedImage': _compressed,
}


# --- mutations -------------------------------------------------------------------------------


def leaves(message: Any, path: tuple[Any, ...] = ()) -> Iterator[tuple[tuple[Any, ...], str]]:
    """(path, field type) of every field, nested fields and sequence items included."""
    for name, text in type(message).get_fields_and_field_types().items():
        kind, element, _ = split_type(text)
        value = getattr(message, name)
        yield (*path, name), text
        if kind == 'one' and '/' in element:
            yield from leaves(value, (*path, name))
        elif '/' in element:
            for index, item in enumerate(value):
                yield from leaves(item, (*path, name, index))
        elif kind != 'one' and element in ('double', 'float') and len(value):
            for index in range(len(value)):
                yield (*path, name, index), element


def extreme_value(draw: Any, text: str, rng: np.random.Generator) -> Any:
    kind, element, size = split_type(text)
    if kind == 'one' and '/' in element:
        return sane(rng, element)
    if kind == 'one':
        return draw(scalar_values(element, True))
    if kind == 'array':
        assert size is not None
        if '/' in element:
            return [sane(rng, element) for _ in range(size)]
        values = [draw(scalar_values(element, True)) for _ in range(size)]
        return bytes(values) if element in ('uint8', 'octet') else values
    count = draw(st.sampled_from((0, 1, 2, 7)) | st.integers(0, 40))
    if size is not None:
        count = min(count, size)
    if element in ('uint8', 'octet'):
        return draw(st.binary(max_size=count * 64))
    if '/' in element:
        return [sane(rng, element) for _ in range(min(count, 12))]
    return [draw(scalar_values(element, True)) for _ in range(count)]


def set_path(message: Any, path: tuple[Any, ...], value: Any) -> None:
    target = message
    for step in path[:-1]:
        target = target[step] if isinstance(step, int) else getattr(target, step)
    last = path[-1]
    if isinstance(last, int):
        target[last] = value
    else:
        setattr(target, last, value)


@dataclass
class Recipe:
    """A message to feed: ``message``, of which the fields at ``stamped`` get the feed's
    stamp unless a mutation set them (``keep_stamp``)."""

    message: Any
    keep_stamp: bool
    mutations: list[str] = field(default_factory=list)


@st.composite
def fuzzed(draw: Any, type_name: str) -> Recipe:
    """A sane message with 0-4 fields made extreme, or (one in eight) all fields random."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    message = sane(rng, type_name)
    if draw(st.integers(0, 7)) == 0:
        for path, text in list(leaves(message))[:60]:
            if len(path) == 1:
                set_path(message, path, extreme_value(draw, text, rng))
        return Recipe(message, True, ['all fields'])
    recipe = Recipe(message, False)
    for _ in range(draw(st.integers(0, 4))):
        candidates = list(leaves(message))
        path, text = draw(st.sampled_from(candidates))
        try:
            set_path(message, path, extreme_value(draw, text, rng))
        except (AssertionError, TypeError, ValueError, IndexError):
            continue  # a value the message class itself refuses: no such message on the wire
        recipe.mutations.append('.'.join(str(p) for p in path))
        recipe.keep_stamp |= 'stamp' in path
    return recipe


# --- the nodes -------------------------------------------------------------------------------


def non_finite(message: Any, path: str = '') -> list[str]:
    """The paths of NaN or inf float values in a message."""
    found: list[str] = []
    if not hasattr(message, 'get_fields_and_field_types'):
        return found
    for name, text in message.get_fields_and_field_types().items():
        kind, element, _ = split_type(text)
        value = getattr(message, name)
        where = f'{path}.{name}' if path else name
        if '/' in element:
            for index, item in enumerate([value] if kind == 'one' else value):
                found += non_finite(item, where if kind == 'one' else f'{where}[{index}]')
        elif element in ('double', 'float'):
            values = [value] if kind == 'one' else list(value)
            if not all(math.isfinite(v) for v in values):
                found.append(where)
    return found


class _Logger:
    """Stands in for a node's logger: keeps (level, text)."""

    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def _add(self, level: str) -> Callable[..., bool]:
        def log(text: str, **_: Any) -> bool:
            self.lines.append((level, str(text)))
            return True

        return log

    def __getattr__(self, name: str) -> Any:
        if name in ('debug', 'info', 'warning', 'warn', 'error', 'fatal'):
            return self._add(name)
        raise AttributeError(name)


REJECTION_WORDS = ('dropped', 'refused', 'rejected', 'ignored', 'discarded')


@dataclass
class Outcome:
    """What one fed message caused."""

    escaped: str | None = None
    non_finite: list[str] = field(default_factory=list)
    uncounted: list[str] = field(default_factory=list)


class NodeUnderFuzz:
    """A node with recorded publishers and logger, and its inputs by topic."""

    def __init__(self, node: Node) -> None:
        self.node = node
        self.logger = _Logger()
        node._logger = self.logger  # type: ignore[attr-defined]
        self.published: list[tuple[str, Any]] = []
        for publisher in node.publishers:
            topic = publisher.topic_name
            if topic.endswith('/diagnostics') or topic == '/rosout':
                continue
            publisher.publish = (  # type: ignore[method-assign]
                lambda message, t=topic: self.published.append((t, message))
            )
        self.inputs = {s.topic_name: s for s in node.subscriptions}
        self.stamp_ns = 1_700_000_000 * 10**9

    def next_stamp(self) -> int:
        self.stamp_ns += 50_000_000
        return self.stamp_ns

    def counts(self) -> dict[str, int]:
        return dict(self.node._counts())  # type: ignore[attr-defined]

    def _deliver(self, topic: str, recipe: Recipe) -> None:
        if not recipe.keep_stamp:
            stamp_ns = self.next_stamp()
            for path, _ in leaves(recipe.message):
                if path[-1] == 'stamp':
                    set_path(recipe.message, (*path, 'sec'), stamp_ns // 10**9)
                    set_path(recipe.message, (*path, 'nanosec'), stamp_ns % 10**9)
        subscription = self.inputs[topic]
        message: Any = recipe.message
        if subscription.raw:  # a node that takes the serialized bytes gets them, as from DDS
            message = serialize_message(message)
        subscription.callback(message, {})

    def feed(self, topic: str, recipe: Recipe, others: dict[str, Recipe]) -> Outcome:
        """Feed ``recipe`` on ``topic``, then ``others`` (sane, by topic), then the timers."""
        outcome = Outcome()
        self.published.clear()
        self.logger.lines.clear()
        before = self.counts()
        try:
            self._deliver(topic, recipe)
        except Exception:
            outcome.escaped = traceback.format_exc(limit=-4)
            return outcome
        after = self.counts()
        complaints = [
            text
            for level, text in self.logger.lines
            if level in ('error', 'fatal')
            or (level in ('warning', 'warn') and any(w in text for w in REJECTION_WORDS))
        ]
        if complaints and after == before:
            outcome.uncounted = complaints
        try:
            for other, message in others.items():
                self._deliver(other, message)
            for timer in self.node.timers:
                if not timer.is_canceled():
                    timer.callback()
        except Exception:
            outcome.escaped = 'after the fuzzed message: ' + traceback.format_exc(limit=-4)
        for out_topic, message in self.published:
            outcome.non_finite += [f'{out_topic}: {p}' for p in non_finite(message)]
        return outcome


# --- the targets -----------------------------------------------------------------------------


def _node(module: str, name: str, **parameters: Any) -> Callable[[], Node]:
    def make() -> Node:
        from rclpy.parameter import Parameter

        cls = getattr(importlib.import_module(module), name)
        overrides = [Parameter(key, value=value) for key, value in parameters.items()]
        return cls(parameter_overrides=overrides)  # type: ignore[no-any-return]

    return make


MARKERS = 'marker_detector.detector.node'
BRIDGE = 'marker_detector.apriltag_bridge.node'
TRACKER = 'monoslam_shadow_node.feature_tracker.node'
NODES: dict[str, Callable[[], Node]] = {
    'marker_detector': _node(MARKERS, 'MarkerDetectorNode'),
    'marker_detector (compressed)': _node(
        MARKERS, 'MarkerDetectorNode', image_transport='compressed', extrinsics_source='parameters'
    ),
    'apriltag_bridge': _node(BRIDGE, 'AprilTagBridgeNode'),
    'feature_tracker': _node(
        TRACKER, 'FeatureTrackerNode', use_predictions=True, publish_debug_image=True
    ),
    'feature_tracker (compressed)': _node(
        TRACKER, 'FeatureTrackerNode', image_transport='compressed'
    ),
    'monoslam': _node('monoslam_shadow_node.monoslam.node', 'MonoSlamNode'),
    'shadow_filter': _node('monoslam_shadow_node.shadow_filter.node', 'ShadowFilterNode'),
    'odometry_ingest': _node('em_sam_node.odometry_ingest.node', 'OdometryIngestNode'),
    'em_sam_mapper': _node('em_sam_node.mapper.node', 'EmSamMapperNode'),
}
INPUTS: dict[str, tuple[str, ...]] = {
    'marker_detector': ('/camera/image_raw', '/camera/camera_info', '/tf_static'),
    'marker_detector (compressed)': ('/camera/image_raw/compressed',),
    'apriltag_bridge': ('/detections', '/tf', '/tf_static', '/camera/camera_info'),
    'feature_tracker': (
        '/camera/image_raw', '/camera/camera_info', '/features/predicted', '/shadow/tracks',
        '/shadow/static_features', '/monoslam/revoked',
    ),
    'feature_tracker (compressed)': ('/camera/image_raw/compressed',),
    'monoslam': (
        '/features', '/fiducials', '/camera/camera_info', '/shadow/static_features',
        '/shadow/tracks',
    ),
    'shadow_filter': (
        '/features', '/monoslam/pose', '/monoslam/pose/link', '/camera/camera_info',
        '/monoslam/revoked',
    ),
    'odometry_ingest': ('/odom', '/landmark_observations', '/slam/end_of_input'),
    'em_sam_mapper': ('/odometry_increments', '/landmark_observations'),
}  # fmt: skip
"""The inputs fuzzed per node (the compressed variants: the inputs the raw ones lack)."""

FIELDLESS = ('/slam/end_of_input',)
"""Inputs of a type with no field (std_msgs/Empty): nothing to fuzz, only listed."""

TARGETS = [
    (node, topic) for node, topics in INPUTS.items() for topic in topics if topic not in FIELDLESS
]


def type_name(subscription: Any) -> str:
    cls = subscription.msg_type
    return f'{cls.__module__.split(".")[0]}/{cls.__name__}'


def sane_others(under: NodeUnderFuzz, topic: str, draw: Any) -> dict[str, Recipe]:
    """One sane message for each input but ``topic`` (camera_info and tf first)."""
    order = sorted(under.inputs, key=lambda t: ('camera_info' not in t and 'tf' not in t, t))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    return {
        other: Recipe(sane(rng, type_name(under.inputs[other])), False)
        for other in order
        if other != topic
    }
