"""Grey images of the dynamic scene by exact ray casting; see docs/design/simulation.md."""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slam_core.arrays import BoolArray, Float32Array, FloatArray
from slam_core.render.patch import NEAR_M, UNIT_SQUARE, plane_hits
from slam_core.render.texture import sample_bilinear
from slam_sim.core.camera_effects import CameraEffects
from slam_sim.core.dynamic_atlas import GUTTER, build_charts
from slam_sim.core.dynamic_config import DynamicSceneConfig
from slam_sim.core.dynamic_options import RenderOptions
from slam_sim.core.dynamic_rays import (
    Direction,
    Hits,
    Int32Array,
    RayBundle,
    box_corners,
    box_entry,
    grid_rays,
    part,
    room_exit,
    sphere_entry,
    subpixel_rays,
    surface_edges,
)
from slam_sim.core.dynamic_scene import build_scene
from slam_sim.core.init_target import InitTarget, target_pixels
from slam_sim.core.office_view import SceneStyle

LABEL_NOTHING = -2
LABEL_STATIC = -1
TARGET_STANDOFF_M = 1e-3
DEFAULT_OBJECT_RADIUS_M = 0.3
EFFECTS_SPAWN_KEY = 5
"""``SeedSequence(seed, spawn_key=(5,))`` drives the image effects (the textures use 6)."""


@dataclass(frozen=True)
class RenderedFrame:
    """One frame: pose, image (H, W) uint8, labels (H, W), depth (H, W) m, target corners."""

    index: int
    time_s: float
    rotation: FloatArray
    position_m: FloatArray
    image: NDArray[np.uint8]
    labels: NDArray[np.int16]
    depth_m: Float32Array
    target_corners_px: FloatArray | None


class DynamicRenderer:
    """Renders the dynamic scene of ``config`` and ``seed``; frame k is at k / rate_hz s."""

    def __init__(
        self,
        config: DynamicSceneConfig,
        seed: int,
        *,
        options: RenderOptions | None = None,
        target: InitTarget | None = None,
    ) -> None:
        self.config, self.seed = config, seed
        self.options = options if options is not None else RenderOptions()
        self.target = target if target is not None else InitTarget()
        self.camera = config.camera()
        self.scene = build_scene(config, seed)
        self.object_radius_m = config.object_radius_m or DEFAULT_OBJECT_RADIUS_M
        self._rays = grid_rays(self.camera)
        self._subpixels: tuple[Float32Array, BoolArray] | None = None  # on first use
        self._charts = build_charts(
            self.scene, self.target, self.object_radius_m, self.options, seed
        )
        self._planar = len(self._charts.coeff)
        self._labels = np.concatenate(
            [np.full(self._planar, LABEL_STATIC), np.arange(len(self.scene.objects))]
        ).astype(np.int16)
        self._effects = None
        if self.options.effects is not None:
            seed_sequence = np.random.SeedSequence(seed, spawn_key=(EFFECTS_SPAWN_KEY,))
            self._effects = CameraEffects(self.options.effects, self.camera, seed_sequence)

    def time_s(self, frame_index: int) -> float:
        """Return the run time s of frame ``frame_index``."""
        if frame_index < 0:
            raise ValueError(f'frame_index = {frame_index} must be >= 0')
        return frame_index / self.config.rate_hz

    def pose(self, frame_index: int) -> tuple[FloatArray, FloatArray]:
        """Return R_world_camera (3, 3) and the optical centre (3,) m in map at a frame."""
        times = np.array([self.time_s(frame_index)])
        path = self.scene.camera_path
        return path.rotations_at(times)[0], path.positions_at(times)[0]

    def object_centres(self, frame_index: int) -> tuple[FloatArray, BoolArray]:
        """Return the object centres (K, 3) m in map at a frame and whether each exists."""
        times = np.array([self.time_s(frame_index)])
        centres = [motion.states_at(times)[0][0] for motion in self.scene.objects]
        point_exists = self.scene.points_exist_at(times)[0]
        owner = self.scene.point_object
        exists = [bool(point_exists[owner == index].all()) for index in range(len(centres))]
        return np.array(centres).reshape(-1, 3), np.array(exists, dtype=bool)

    def render(self, frame_index: int) -> RenderedFrame:
        """Return frame ``frame_index``: image, labels, depth and target truth."""
        rotation, position = self.pose(frame_index)
        centres, exists = self.object_centres(frame_index)
        hits, target_seen = self._cast(self._rays, rotation, position, centres, exists)
        grey = self._shade(hits, self._rays, position, centres)
        edge = surface_edges(hits.chart, self._rays.valid)
        if self.options.supersample > 1 and edge.any():
            grey[edge] = self._supersample(edge, rotation, position, centres, exists, grey[edge])
        time_s = self.time_s(frame_index)
        if self._effects is None:
            image = np.clip(np.rint(grey), 0, 255).astype(np.uint8)
        else:
            image = self._effects.apply(
                grey, frame_index=frame_index, time_s=time_s, yaw_rate_radps=0.0
            )
        corners = target_pixels(self.target, self.camera, rotation, position)
        return RenderedFrame(
            index=frame_index,
            time_s=time_s,
            rotation=rotation,
            position_m=position,
            image=image,
            labels=self._label(hits.chart),
            depth_m=np.where(hits.chart >= 0, hits.depth, np.float32(np.inf)),
            target_corners_px=corners if target_seen else None,
        )

    def render_all(self, indices: Iterable[int], *, threads: int = 2) -> Iterator[RenderedFrame]:
        """Yield ``render(k)`` for each k of ``indices``, in order, ``threads`` at a time."""
        if threads < 1:
            raise ValueError(f'threads = {threads} must be >= 1')
        if self.options.supersample > 1 and self._subpixels is None:  # once, not per thread
            self._subpixels = subpixel_rays(self.camera, self.options.supersample)
        with ThreadPoolExecutor(threads, thread_name_prefix='render') as pool:
            pending: deque[Future[RenderedFrame]] = deque()
            for index in indices:
                pending.append(pool.submit(self.render, index))
                if len(pending) > 2 * threads:  # bounded look-ahead: memory stays flat
                    yield pending.popleft().result()
            while pending:
                yield pending.popleft().result()

    def probe(
        self, frame_index: int, pixels: FloatArray
    ) -> tuple[Float32Array, NDArray[np.int16]]:
        """Return the depth (N,) m and label (N,) of what raw pixels (N, 2) see at a frame."""
        if np.size(pixels) == 0:
            return np.zeros(0, np.float32), np.zeros(0, np.int16)
        rotation, position = self.pose(frame_index)
        centres, exists = self.object_centres(frame_index)
        normalized, valid = self.camera.unproject(np.asarray(pixels).reshape(1, -1, 2))
        rays = RayBundle.of(normalized, np.zeros(valid.shape), valid)
        hits, _ = self._cast(rays, rotation, position, centres, exists)
        depth = np.where(hits.chart >= 0, hits.depth, np.float32(np.inf))
        return depth[0].astype(np.float32), self._label(hits.chart)[0]

    def _label(self, chart: Int32Array) -> NDArray[np.int16]:
        labels = self._labels[np.maximum(chart, 0)]
        return np.where(chart >= 0, labels, np.int16(LABEL_NOTHING)).astype(np.int16)

    def _supersample(
        self,
        edge: BoolArray,
        rotation: FloatArray,
        position: FloatArray,
        centres: FloatArray,
        exists: BoolArray,
        centre_grey: Float32Array,
    ) -> Float32Array:
        """Return the grey (M,) of the edge pixels, averaged over n x n rays per pixel."""
        n = self.options.supersample
        rows, cols = np.nonzero(edge)
        if self._subpixels is None:
            self._subpixels = subpixel_rays(self.camera, n)
        grid, valid_grid = self._subpixels
        normalized, valid = grid[rows, cols], valid_grid[rows, cols]
        angle = np.broadcast_to(self._rays.angle_rad[rows, cols][:, None] / n, valid.shape)
        rays = RayBundle.of(normalized, angle, valid)
        hits, _ = self._cast(rays, rotation, position, centres, exists)
        grey = self._shade(hits, rays, position, centres)
        count = valid.sum(axis=1)
        mean = np.where(valid, grey, 0.0).sum(axis=1) / np.maximum(count, 1)
        return np.where(count > 0, mean, centre_grey).astype(np.float32)

    def _cast(
        self,
        rays: RayBundle,
        rotation: FloatArray,
        position: FloatArray,
        centres: FloatArray,
        exists: BoolArray,
    ) -> tuple[Hits, bool]:
        """Return the nearest hits of ``rays`` and whether the target square is unoccluded."""
        room = self.scene.room
        if not np.all((position > 0.0) & (position < room.size_m)):
            raise ValueError(f'camera centre {position.tolist()} m is outside the room')
        r = rotation.astype(np.float32)
        direction: Direction = tuple(
            (r[i, 0] * rays.x + r[i, 1] * rays.y + r[i, 2]).astype(np.float32) for i in range(3)
        )
        depth, chart = room_exit(position, direction, np.asarray(room.size_m))
        hits = Hits(depth, chart, direction)
        boxes = zip(room.cabinets_min_m, room.cabinets_max_m, strict=True)
        for index, (low, high) in enumerate(boxes, start=1):
            region = rays.region((box_corners(low, high) - position) @ rotation)
            if region is not None:
                box_depth, face = box_entry(position, part(direction, region), low, high)
                hits.keep_nearer(region, box_depth, face + 6 * index)
        cube = box_corners(np.full(3, -self.object_radius_m), np.full(3, self.object_radius_m))
        radius = self.object_radius_m
        for index in np.flatnonzero(exists).tolist():
            centre = centres[index]
            outside = float(np.sum((position - centre) ** 2)) > radius**2
            region = rays.region((centre + cube - position) @ rotation) if outside else None
            if region is not None:
                sphere_depth = sphere_entry(
                    position, part(direction, region), rays.norm2[region], centre, radius
                )
                hits.keep_nearer(region, sphere_depth, self._planar + index)
        seen = self._cast_target(hits, rays, rotation, position)
        hits.chart[~rays.valid] = -1
        return hits, seen

    def _cast_target(
        self, hits: Hits, rays: RayBundle, rotation: FloatArray, position: FloatArray
    ) -> bool:
        """Draw the target's board; return whether its square is seen wherever the rays meet it."""
        target = self.target
        axes = np.asarray(target.rotation, dtype=np.float64)
        paper_half = 0.5 * SceneStyle(side_m=target.side_m).paper_m
        paper = paper_half * UNIT_SQUARE
        region = rays.region((target.centre_m + paper @ axes.T - position) @ rotation)
        if region is None:
            return False
        direction = part(hits.direction, region)
        plane = plane_hits(direction, position - target.centre_m, axes, dtype=np.float32)
        depth, normal_rate = plane.depth, plane.normal_rate
        extent = np.maximum(np.abs(plane.local_x), np.abs(plane.local_y))
        board = (depth > NEAR_M) & (extent <= paper_half)
        square = board & (normal_rate < 0.0) & (extent <= 0.5 * target.side_m)
        square &= rays.valid[region]
        current = hits.depth[region]
        # The board wins over what lies less than TARGET_STANDOFF_M in front of it.
        wins = board & (depth - np.float32(TARGET_STANDOFF_M) < current)
        hits.depth[region] = np.where(wins, depth, current)
        face = np.where(normal_rate < 0.0, self._planar - 2, self._planar - 1)
        hits.chart[region] = np.where(wins, face, hits.chart[region])
        return bool(square.any()) and bool(np.all(wins | ~square))

    def _shade(
        self, hits: Hits, rays: RayBundle, position: FloatArray, centres: FloatArray
    ) -> Float32Array:
        """Return the filtered texture grey (A, B) of the hits (0 where there are none)."""
        charts, options = self._charts, self.options
        chart = hits.chart
        planar = np.clip(chart, 0, self._planar - 1)
        depth = np.where(chart >= 0, hits.depth, np.float32(1.0))
        point = [np.float32(position[i]) + depth * hits.direction[i] for i in range(3)]
        coeff = charts.coeff[planar]
        col = coeff[..., 0, 3] + sum(coeff[..., 0, i] * point[i] for i in range(3))
        row = coeff[..., 1, 3] + sum(coeff[..., 1, i] * point[i] for i in range(3))
        normal = charts.normal[planar]
        rate = np.abs(sum(normal[..., i] * hits.direction[i] for i in range(3)))
        density = charts.density[planar]
        sphere = np.flatnonzero(chart.ravel() >= self._planar)
        if sphere.size:
            self._sphere_texels(sphere, chart, point, centres, hits, (col, row, rate, density))
        footprint = depth * rays.norm2 * rays.angle_rad * density
        footprint /= np.maximum(rate, np.float32(0.02) * np.sqrt(rays.norm2))
        with np.errstate(divide='ignore'):
            lod = np.log2(footprint) + np.float32(options.lod_bias)
        lod = np.clip(np.nan_to_num(lod, nan=0.0), 0.0, len(charts.levels) - 1)
        grey = np.zeros(chart.shape, dtype=np.float32)
        for level, texels in enumerate(charts.levels):
            weight = np.maximum(np.float32(1.0) - np.abs(lod - np.float32(level)), 0.0)
            if not weight.any():
                continue
            scale = np.float32(0.5**level)
            grey += weight * sample_bilinear(texels, col * scale, row * scale)
        return np.where(chart >= 0, grey, np.float32(0.0)).astype(np.float32)

    def _sphere_texels(
        self,
        flat: NDArray[np.intp],
        chart: Int32Array,
        point: list[Float32Array],
        centres: FloatArray,
        hits: Hits,
        out: tuple[Float32Array, Float32Array, Float32Array, Float32Array],
    ) -> None:
        """Write the sphere hits' texel, normal rate and density into ``out``."""
        radius = self.object_radius_m
        obj = chart.ravel()[flat] - self._planar
        unit = np.stack([p.ravel()[flat] for p in point], axis=1) - centres[obj]
        unit /= np.linalg.norm(unit, axis=1, keepdims=True)
        axis = np.argmax(np.abs(unit), axis=1)
        rows = np.arange(len(flat))
        major = unit[rows, axis]
        a = unit[rows, (axis + 1) % 3] / np.abs(major)
        b = unit[rows, (axis + 2) % 3] / np.abs(major)
        face = 2 * axis + (major < 0.0)
        half = 0.5 * self.options.object_face_texels
        offset = self._charts.sphere_offset[obj, face]
        direction = np.stack([d.ravel()[flat] for d in hits.direction], axis=1)
        col, row, rate, density = (array.reshape(-1) for array in out)
        col[flat] = offset[:, 0] + GUTTER - 0.5 + (a + 1.0) * half
        row[flat] = offset[:, 1] + GUTTER - 0.5 + (b + 1.0) * half
        rate[flat] = np.abs(np.sum(unit * direction, axis=1))
        density[flat] = half / radius * (1.0 + a * a + b * b)
