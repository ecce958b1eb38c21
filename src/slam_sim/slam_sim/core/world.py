"""The EM-SAM paper's office world (section IV); see docs/design/simulation.md."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam_core.arrays import BoolArray, FloatArray, IntArray
from slam_sim.core.geometry import unit_vectors

OFFICE_1 = 'office_1'
CORRIDOR = 'corridor'
OFFICE_2 = 'office_2'
# Sides of a room: the outward wall direction and the inward marker normal.
_Marker = tuple[tuple[float, float], tuple[float, float], str]
_INWARD = {'west': (1.0, 0.0), 'east': (-1.0, 0.0), 'south': (0.0, 1.0), 'north': (0.0, -1.0)}


@dataclass(frozen=True)
class Room:
    """An axis-aligned room: name and corners (x, y) in m."""

    name: str
    min_m: tuple[float, float]
    max_m: tuple[float, float]

    @property
    def center_m(self) -> FloatArray:
        """The room centre (2,) in m."""
        return np.add(self.min_m, self.max_m, dtype=np.float64) / 2.0

    def contains(self, points_m: FloatArray, *, margin_m: float = 0.0) -> BoolArray:
        """Return (N,) True for points (N, 2) at least ``margin_m`` inside the room."""
        low = np.asarray(self.min_m) + margin_m
        high = np.asarray(self.max_m) - margin_m
        return np.asarray(np.all((points_m >= low) & (points_m <= high), axis=-1), dtype=bool)


@dataclass(frozen=True)
class MarkerSet:
    """Markers: ids (N,), positions (N, 2) m, unit face normals (N, 2), room names (N)."""

    ids: IntArray
    positions_m: FloatArray
    normals: FloatArray
    rooms: tuple[str, ...]


@dataclass(frozen=True)
class OfficeWorld:
    """Walls (W, 2, 2) in m and the three rooms; doors and corridor centred on door_y_m."""

    walls_m: FloatArray
    office_1: Room
    corridor: Room
    office_2: Room
    door_y_m: float
    door_width_m: float

    @property
    def rooms(self) -> tuple[Room, Room, Room]:
        """Office 1, corridor, office 2."""
        return self.office_1, self.corridor, self.office_2

    def room_of(self, points_m: FloatArray) -> tuple[str, ...]:
        """Return the room name of each point (N, 2) ('' outside every room)."""
        names = np.full(points_m.shape[0], '', dtype=object)
        for room in reversed(self.rooms):  # a door line belongs to the office
            names[room.contains(points_m)] = room.name
        return tuple(str(name) for name in names)


def build_world(
    *,
    office_size_m: float,
    corridor_length_m: float,
    corridor_width_m: float,
    door_width_m: float,
) -> OfficeWorld:
    """Return the walls and rooms of two square offices joined by a straight corridor."""
    if min(office_size_m, corridor_length_m, corridor_width_m, door_width_m) <= 0.0:
        raise ValueError('office size, corridor length and width and door width must be > 0')
    if not door_width_m + 0.4 <= corridor_width_m <= office_size_m - 1.0:
        raise ValueError(
            f'corridor width {corridor_width_m} m must be at least the door width '
            f'{door_width_m} m + 0.4 m (room for end-wall markers) and at most the office '
            f'size {office_size_m} m - 1 m'
        )
    side, x_far = office_size_m, office_size_m + corridor_length_m
    center_y = side / 2.0
    low, high = center_y - corridor_width_m / 2.0, center_y + corridor_width_m / 2.0
    door_low, door_high = center_y - door_width_m / 2.0, center_y + door_width_m / 2.0
    walls = []
    for x0 in (0.0, x_far):
        door_x = x0 + side if x0 == 0.0 else x0
        solid_x = x0 if x0 == 0.0 else x0 + side
        walls += [
            ((x0, 0.0), (x0 + side, 0.0)),
            ((x0, side), (x0 + side, side)),
            ((solid_x, 0.0), (solid_x, side)),
            ((door_x, 0.0), (door_x, door_low)),
            ((door_x, door_high), (door_x, side)),
        ]
    walls += [((side, low), (x_far, low)), ((side, high), (x_far, high))]
    return OfficeWorld(
        walls_m=np.asarray(walls, dtype=np.float64),
        office_1=Room(OFFICE_1, (0.0, 0.0), (side, side)),
        corridor=Room(CORRIDOR, (side, low), (x_far, high)),
        office_2=Room(OFFICE_2, (x_far, 0.0), (x_far + side, side)),
        door_y_m=center_y,
        door_width_m=door_width_m,
    )


def _wall_markers(room: Room, side: str, fractions: tuple[float, ...]) -> list[_Marker]:
    """Markers on one wall of ``room`` at ``fractions`` of its length (west/south first)."""
    (x0, y0), (x1, y1) = room.min_m, room.max_m
    markers: list[_Marker] = []
    for fraction in fractions:
        if side in ('west', 'east'):
            position = (x0 if side == 'west' else x1, y0 + fraction * (y1 - y0))
        else:
            position = (x0 + fraction * (x1 - x0), y0 if side == 'south' else y1)
        markers.append((position, _INWARD[side], room.name))
    return markers


def static_markers(world: OfficeWorld) -> MarkerSet:
    """Return the 29 wall markers: office 1 (ids 0-11), corridor (12-19), office 2."""
    office_1, corridor, office_2 = world.rooms
    markers = (
        _wall_markers(office_1, 'west', (0.25, 0.5, 0.75))
        + _wall_markers(office_1, 'north', (0.18, 0.39, 0.61, 0.82))
        + _wall_markers(office_1, 'south', (0.25, 0.5, 0.75))
        + _wall_markers(office_1, 'east', (0.15, 0.85))
        + _wall_markers(corridor, 'north', (0.2, 0.5, 0.8))
        + _wall_markers(corridor, 'south', (0.35, 0.65, 0.9))
    )
    # The corridor's end walls are the offices' door walls seen from the corridor side.
    (x_low, y_low), (x_high, y_high) = corridor.min_m, corridor.max_m
    door_low = world.door_y_m - world.door_width_m / 2.0
    door_high = world.door_y_m + world.door_width_m / 2.0
    markers += [
        ((x_low, (y_low + door_low) / 2.0), _INWARD['west'], CORRIDOR),
        ((x_high, (door_high + y_high) / 2.0), _INWARD['east'], CORRIDOR),
    ]
    markers += (
        _wall_markers(office_2, 'north', (0.25, 0.5, 0.75))
        + _wall_markers(office_2, 'south', (0.25, 0.5, 0.75))
        + _wall_markers(office_2, 'east', (0.25, 0.5, 0.75))
    )
    return MarkerSet(
        ids=np.arange(len(markers), dtype=np.int64),
        positions_m=np.array([m[0] for m in markers], dtype=np.float64),
        normals=np.array([m[1] for m in markers], dtype=np.float64),
        rooms=tuple(m[2] for m in markers),
    )


def desk_spots(
    room: Room,
    rng: np.random.Generator,
    count: int,
    *,
    door_direction_rad: float,
    door_clearance_rad: float = 0.5,
    radius_fraction: tuple[float, float] = (0.34, 0.40),
    facing_spread_rad: float = 0.8,
    min_separation_m: float = 0.35,
) -> tuple[FloatArray, FloatArray]:
    """Return ``count`` desk marker positions (count, 2) m and face normals (count, 2)."""
    center = room.center_m
    side = room.max_m[0] - room.min_m[0]
    positions: list[FloatArray] = []
    for _ in range(200 * max(count, 1)):
        if len(positions) == count:
            break
        angle = door_direction_rad + rng.uniform(
            door_clearance_rad, 2.0 * np.pi - door_clearance_rad
        )
        radius = side * rng.uniform(*radius_fraction)
        candidate = center + radius * unit_vectors(angle)
        if all(np.linalg.norm(candidate - other) >= min_separation_m for other in positions):
            positions.append(candidate)
    if len(positions) < count:
        raise ValueError(
            f'cannot place {count} desk markers {min_separation_m} m apart in {room.name}; '
            'lower the moveable marker count'
        )
    spots = np.array(positions, dtype=np.float64).reshape(count, 2)
    to_center = np.arctan2(center[1] - spots[:, 1], center[0] - spots[:, 0])
    facing = to_center + rng.uniform(-facing_spread_rad, facing_spread_rad, count)
    return spots, unit_vectors(facing)
