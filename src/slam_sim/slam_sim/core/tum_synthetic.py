"""A small synthetic TUM-layout RGB-D sequence for tests; see docs/design/simulation.md."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from slam_core.arrays import FloatArray
from slam_sim.core.tum_rgbd import Intrinsics

START_NS = 1_500_000_000_000_000_000
TEXTURE_PX_PER_M = 400.0
WALL_CORNER_M = 2.0


@dataclass(frozen=True)
class SyntheticTum:
    """The synthetic sequence's settings; sizes in px, m, s."""

    images: int = 45
    rate_hz: float = 30.0
    width: int = 320
    height: int = 240
    intrinsics: Intrinsics = field(default_factory=lambda: Intrinsics(300.0, 300.0, 160.0, 120.0))
    wall_z_m: float = 3.0
    board_z_m: float = 1.5
    board_side_m: float = 0.8
    board_start_x_m: float = -1.5
    board_speed_mps: float = 1.0
    camera_speed_mps: float = 0.2
    depth_every: int = 3
    depth_offset_ns: int = 5_000_000
    truth_rate_hz: float = 50.0
    seed: int = 0

    def stamp_ns(self, image: int) -> int:
        """Return the stamp (int ns, whole microseconds) of an image."""
        return START_NS + 1000 * round(image * 1e6 / self.rate_hz)

    def camera_x_m(self, stamp_ns: int) -> float:
        """Return the camera's x (m) at a stamp."""
        return self.camera_speed_mps * (stamp_ns - START_NS) / 1e9

    def board_x_m(self, stamp_ns: int) -> float:
        """Return the board centre's x (m) at a stamp (it is centred on y = 0)."""
        return self.board_start_x_m + self.board_speed_mps * (stamp_ns - START_NS) / 1e9


def _texture(rng: np.random.Generator, size_px: int, cell_px: int) -> np.ndarray:
    """Return a grey texture (size, size) uint8 of random cells, slightly blurred."""
    cells = rng.integers(0, 256, size=(size_px // cell_px + 1,) * 2).astype(np.uint8)
    texture = np.kron(cells, np.ones((cell_px, cell_px), np.uint8))[:size_px, :size_px]
    return np.asarray(cv2.GaussianBlur(texture, (3, 3), 0.8))


def _draw(texture: np.ndarray, x_m: FloatArray, y_m: FloatArray) -> np.ndarray:
    """Return the texture (tiled) at plane coordinates x, y (H, W) m from its corner."""
    map_x = (x_m * TEXTURE_PX_PER_M).astype(np.float32)
    map_y = (y_m * TEXTURE_PX_PER_M).astype(np.float32)
    return np.asarray(
        cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    )


def render(
    config: SyntheticTum, stamp_ns: int, textures: tuple[np.ndarray, np.ndarray]
) -> tuple[np.ndarray, FloatArray]:
    """Return the grey image (H, W) uint8 and depth (H, W) m at a stamp."""
    k = config.intrinsics
    us, vs = np.meshgrid(np.arange(config.width, dtype=np.float64), np.arange(config.height))
    x_n = np.asarray((us - k.cx) / k.fx, dtype=np.float64)
    y_n = np.asarray((vs - k.cy) / k.fy, dtype=np.float64)
    camera_x = config.camera_x_m(stamp_ns)
    wall, board = textures
    wall_z, board_z, side = config.wall_z_m, config.board_z_m, config.board_side_m
    image = _draw(wall, camera_x + x_n * wall_z + WALL_CORNER_M, y_n * wall_z + WALL_CORNER_M)
    depth = np.full((config.height, config.width), wall_z)
    board_x = camera_x + x_n * board_z - (config.board_x_m(stamp_ns) - side / 2)
    board_y = y_n * board_z + side / 2
    inside = (board_x >= 0) & (board_x < side) & (board_y >= 0) & (board_y < side)
    image[inside] = _draw(board, board_x, board_y)[inside]
    depth[inside] = board_z
    return image, depth


def board_mask(config: SyntheticTum, stamp_ns: int) -> np.ndarray:
    """Return where the board is in the image at a stamp (H, W) bool."""
    textures = (np.zeros((8, 8), np.uint8), np.zeros((8, 8), np.uint8))
    return np.asarray(render(config, stamp_ns, textures)[1] == config.board_z_m)


def write_synthetic_tum(directory: Path, config: SyntheticTum | None = None) -> Path:
    """Write the synthetic sequence into ``directory`` (created) and return it."""
    config = config if config is not None else SyntheticTum()
    rng = np.random.default_rng(config.seed)
    textures = (_texture(rng, 2400, 12), _texture(rng, 400, 24))
    for name in ('rgb', 'depth'):
        (directory / name).mkdir(parents=True, exist_ok=True)
    rgb_lines = ['# color images', '# timestamp filename']
    depth_lines = ['# depth maps', '# timestamp filename']
    for index in range(config.images):
        stamp = config.stamp_ns(index)
        image, _ = render(config, stamp, textures)
        name = f'rgb/{_seconds(stamp)}.jpg'
        cv2.imwrite(str(directory / name), cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
        rgb_lines.append(f'{_seconds(stamp)} {name}')
        if index % config.depth_every == 0:
            depth_stamp = stamp + config.depth_offset_ns
            _, depth = render(config, depth_stamp, textures)
            name = f'depth/{_seconds(depth_stamp)}.png'
            cv2.imwrite(str(directory / name), np.rint(depth * 5000.0).astype(np.uint16))
            depth_lines.append(f'{_seconds(depth_stamp)} {name}')
    truth = ['# ground truth trajectory', '# timestamp tx ty tz qx qy qz qw']
    step_ns = 1000 * round(1e6 / config.truth_rate_hz)
    stamp = config.stamp_ns(0) + step_ns // 4
    while stamp <= config.stamp_ns(config.images - 1) + step_ns:
        truth.append(f'{_seconds(stamp)} {config.camera_x_m(stamp):.6f} 0 0 0 0 0 1')
        stamp += step_ns
    for name, lines in (('rgb.txt', rgb_lines), ('depth.txt', depth_lines),
                        ('groundtruth.txt', truth)):  # fmt: skip
        (directory / name).write_text('\n'.join(lines) + '\n', encoding='utf-8')
    return directory


def _seconds(stamp_ns: int) -> str:
    """Return int ns as decimal seconds with 6 decimals, as TUM writes them (exact to 1 us)."""
    return f'{stamp_ns // 1_000_000_000}.{stamp_ns % 1_000_000_000 // 1000:06d}'


def write_tum_excerpt(source: Path, target: Path, rgb: int, depth: int, truth: int) -> Path:
    """Write ``source``'s lists cut to their first rows into ``target``; return it."""
    target.mkdir(parents=True)
    for name, rows in (('rgb.txt', rgb), ('depth.txt', depth), ('groundtruth.txt', truth)):
        lines = (source / name).read_text(encoding='utf-8').splitlines()
        kept = [line for line in lines if not line.startswith('#')][:rows]
        if name != 'groundtruth.txt':
            kept = [f'{line.split()[0]} {source / line.split()[1]}' for line in kept]
        (target / name).write_text('\n'.join(kept) + '\n', encoding='utf-8')
    return target
