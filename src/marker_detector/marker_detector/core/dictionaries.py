"""Marker dictionaries by name: the AprilTag families (with bit-error correction) and the
ArUco dictionaries of cv2.aruco. Design notes: docs/design/marker_core.md"""

from __future__ import annotations

import re
from collections.abc import Mapping
from types import MappingProxyType

import cv2

DEFAULT_DICTIONARY = 'DICT_APRILTAG_36h11'

_APRILTAG_FAMILIES = ('36h11', '25h9', '16h5', '36h10')
_ARUCO_SIZES = ('4X4', '5X5', '6X6', '7X7')
_ARUCO_COUNTS = ('50', '100', '250', '1000')

_NAMES = (
    *(f'DICT_APRILTAG_{family}' for family in _APRILTAG_FAMILIES),
    *(f'DICT_{size}_{count}' for size in _ARUCO_SIZES for count in _ARUCO_COUNTS),
    'DICT_ARUCO_ORIGINAL',
)


def _predefined_ids() -> Mapping[str, int]:
    if not hasattr(cv2, 'aruco'):
        raise ImportError(
            'this OpenCV build has no cv2.aruco module; install opencv-python (4.7 or newer) '
            'or a build with the objdetect module'
        )
    ids: dict[str, int] = {}
    for name in _NAMES:
        value = getattr(cv2.aruco, name, None)
        if value is None:
            raise ImportError(f'cv2.aruco has no {name}; OpenCV {cv2.__version__} is too old')
        ids[name] = int(value)
    return MappingProxyType(ids)


DICTIONARIES: Mapping[str, int] = _predefined_ids()
"""Supported dictionary names -> cv2.aruco predefined dictionary ids."""


def apriltag_hamming_distance(name: str) -> int | None:
    """Return the minimum Hamming distance h of an AprilTag family (36h11 -> 11), else None."""
    match = re.fullmatch(r'DICT_APRILTAG_\d+h(\d+)', name)
    return int(match.group(1)) if match else None


def get_dictionary(name: str) -> cv2.aruco.Dictionary:
    """Return the cv2.aruco.Dictionary ``name``; ValueError listing the valid names if unknown."""
    if name not in DICTIONARIES:
        raise ValueError(
            f'unknown marker dictionary {name!r}; valid names: {", ".join(DICTIONARIES)}'
        )
    dictionary = cv2.aruco.getPredefinedDictionary(DICTIONARIES[name])
    hamming = apriltag_hamming_distance(name)
    if hamming is None:
        return dictionary
    return cv2.aruco.Dictionary(dictionary.bytesList, dictionary.markerSize, (hamming - 1) // 2)
