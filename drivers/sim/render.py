"""Rendered camera frames for the simulated workcell: laser spot, plate texture, chessboard.

Pixel convention (OpenCV): the centre of pixel ``(col, row)`` is at ``(u, v) = (col, row)``.
A spot is an elliptical Gaussian sampled at pixel centres,

    I(u, v) = peak * g(u, v) * (1 + speckle * n(u, v)),   g = exp(-q / 2),
    q = [du dv] C^-1 [du dv]^T,  C = Rot(angle) diag(s_major^2, s_minor^2) Rot(angle)^T,

with ``n`` a unit-variance speckle field of about one pixel grain, added to a fixed background
(level + smooth plate texture) and fresh read noise; grey levels are on an 8-bit scale, scaled to
the camera's bit depth, rounded and clipped at full scale.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from drivers.sim.workcell import CameraSpec

#: Number of pre-drawn read-noise images; a frame uses a random window of one of them.
NOISE_POOL = 4
#: Seed of the plate texture (fixed: every frame of one cell sees the same plate).
TEXTURE_SEED = 20150802
#: Margin of the noise images around the frame (px), the range of the random window offset.
NOISE_MARGIN = 64


@dataclass(frozen=True)
class Spot:
    """A spot to render: centre ``(u, v)`` px, ``peak`` grey levels (8-bit scale), shape."""

    u: float
    v: float
    peak: float
    sigma_minor: float
    aspect: float = 1.0
    angle_deg: float = 0.0


@dataclass(frozen=True)
class Chessboard:
    """A chessboard lying on the plate.

    ``pattern`` = inner corners (columns, rows); corner ``(i, j)`` is at
    ``origin + square_mm (i e1 + j e2)`` in the fixed frame with ``e1 = (cos a, sin a)`` and
    ``e2 = (-sin a, cos a)`` (``-e2`` when ``mirrored``), ``a = angle_deg``.
    """

    pattern: tuple[int, int]
    square_mm: float
    origin: tuple[float, float]
    angle_deg: float = 0.0
    mirrored: bool = False

    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        a = math.radians(self.angle_deg)
        e1 = np.array([math.cos(a), math.sin(a)])
        e2 = np.array([-math.sin(a), math.cos(a)]) * (-1.0 if self.mirrored else 1.0)
        return e1, e2

    def corners_mm(self) -> np.ndarray:
        """Inner corners (cols * rows, 2) in the fixed frame, row by row (i fastest)."""
        e1, e2 = self.axes()
        j, i = np.mgrid[0:self.pattern[1], 0:self.pattern[0]]
        ij = np.column_stack([i.ravel(), j.ravel()]).astype(float) * self.square_mm
        return np.asarray(self.origin) + ij[:, 0:1] * e1 + ij[:, 1:2] * e2

    def board_coordinates(self, xy: np.ndarray) -> np.ndarray:
        """Fixed-frame points (..., 2) to board coordinates in squares (corner (0,0) at 0)."""
        e1, e2 = self.axes()
        rx, ry = xy[..., 0] - self.origin[0], xy[..., 1] - self.origin[1]
        return np.stack([rx * e1[0] + ry * e1[1], rx * e2[0] + ry * e2[1]],
                        axis=-1) / self.square_mm


def speckle_field(rng: np.random.Generator, shape: tuple[int, int],
                  grain_px: float = 0.8) -> np.ndarray:
    """Unit-variance Gaussian random field with correlation length ``grain_px`` (float32)."""
    white = rng.standard_normal(shape, dtype=np.float32)
    field = cv2.GaussianBlur(white, (0, 0), grain_px, borderType=cv2.BORDER_REFLECT)
    std = float(field.std())
    return field / std if std > 0 else field


class FrameRenderer:
    """Renders frames of one camera; fixed plate texture, noise and speckle from ``seed``."""

    def __init__(self, camera: CameraSpec, seed: int | None = 0) -> None:
        self.camera = camera
        self.rng = np.random.default_rng(seed)
        w, h = camera.resolution
        self.scale = (2**camera.bit_depth - 1) / 255.0
        self.full_scale = 2**camera.bit_depth - 1
        self.dtype = np.uint8 if camera.bit_depth == 8 else np.uint16
        # the plate texture belongs to the plate: the same for every seed
        plate = np.random.default_rng(TEXTURE_SEED)
        texture = cv2.GaussianBlur(plate.standard_normal((h, w), dtype=np.float32), (0, 0), 6)
        texture *= camera.texture / max(float(texture.std()), 1e-12)
        self.base = ((camera.background + texture) * self.scale).astype(np.float32)
        self._noise = [
            (self.rng.standard_normal((h + NOISE_MARGIN, w + NOISE_MARGIN), dtype=np.float32)
             * np.float32(camera.sensor_noise * self.scale))
            for _ in range(NOISE_POOL)
        ]
        self._plate_xy: np.ndarray | None = None
        self._pool: list[np.ndarray] | None = None

    def spot_for(self, u: float, v: float, peak: float | None = None,
                 angle_deg: float = 0.0) -> Spot:
        """The camera's nominal spot at ``(u, v)``."""
        c = self.camera
        return Spot(u, v, c.spot_peak if peak is None else peak, c.spot_sigma_px,
                    c.spot_aspect, angle_deg)

    def _read_noise(self) -> np.ndarray:
        w, h = self.camera.resolution
        pool = self._noise[int(self.rng.integers(NOISE_POOL))]
        du, dv = (int(x) for x in self.rng.integers(0, NOISE_MARGIN, size=2))
        return pool[dv:dv + h, du:du + w]

    def spot_box(self, spot: Spot) -> tuple[int, int, int, int]:
        """Pixel box ``(u0, v0, u1, v1)`` (end exclusive) holding the spot to +-6 sigma."""
        w, h = self.camera.resolution
        half = math.ceil(6.0 * spot.sigma_minor * spot.aspect)
        return (max(0, math.floor(spot.u) - half), max(0, math.floor(spot.v) - half),
                min(w, math.floor(spot.u) + half + 2), min(h, math.floor(spot.v) + half + 2))

    def add_spot(self, image: np.ndarray, spot: Spot, speckle: float | None = None,
                 origin: tuple[int, int] = (0, 0)) -> None:
        """Add ``spot`` (8-bit grey scale) in place into the float ``image`` whose pixel
        ``[0, 0]`` is the frame's ``(u, v) = origin``, over a +-6 sigma box."""
        u0, v0, u1, v1 = self.spot_box(spot)
        u0, u1 = max(u0, origin[0]), min(u1, origin[0] + image.shape[1])
        v0, v1 = max(v0, origin[1]), min(v1, origin[1] + image.shape[0])
        if u0 >= u1 or v0 >= v1:
            return
        uu = np.arange(u0, u1, dtype=np.float64) - spot.u
        vv = np.arange(v0, v1, dtype=np.float64) - spot.v
        du, dv = np.meshgrid(uu, vv)
        a = math.radians(spot.angle_deg)
        ca, sa = math.cos(a), math.sin(a)
        p = ca * du + sa * dv  # along the major axis
        q = -sa * du + ca * dv
        s_major = spot.sigma_minor * spot.aspect
        g = np.exp(-0.5 * ((p / s_major) ** 2 + (q / spot.sigma_minor) ** 2))
        k = self.camera.speckle if speckle is None else speckle
        if k > 0:
            g *= 1.0 + k * speckle_field(self.rng, g.shape)
        image[v0 - origin[1]:v1 - origin[1], u0 - origin[0]:u1 - origin[0]] += (
            spot.peak * self.scale * g).astype(np.float32)

    def render(self, spots: list[Spot] | tuple[Spot, ...] = (), noise: bool = True,
               speckle: float | None = None) -> np.ndarray:
        """A frame (H, W) with the given spots (none: a background frame, laser off).

        With spots and noise, the frame outside the spots' box is a pre-rendered noisy
        background (one of :data:`NOISE_POOL`) and the box gets fresh read noise: about ten
        times faster than rendering the whole frame, the same statistics where it matters.
        """
        if not spots or not noise:
            image = self.base.copy()
            if noise:
                image += self._read_noise()
            for spot in spots:
                self.add_spot(image, spot, speckle)
            return self._quantise(image)
        boxes = np.array([self.spot_box(s) for s in spots])
        u0, v0 = (int(x) for x in boxes[:, 0:2].min(axis=0))
        u1, v1 = (int(x) for x in boxes[:, 2:4].max(axis=0))
        frame = self._background_pool()[int(self.rng.integers(NOISE_POOL))].copy()
        if u0 >= u1 or v0 >= v1:
            return frame
        patch = self.base[v0:v1, u0:u1] + self.rng.standard_normal(
            (v1 - v0, u1 - u0), dtype=np.float32) * np.float32(
                self.camera.sensor_noise * self.scale)
        for spot in spots:
            self.add_spot(patch, spot, speckle, origin=(u0, v0))
        frame[v0:v1, u0:u1] = self._quantise(patch)
        return frame

    def _background_pool(self) -> list[np.ndarray]:
        if self._pool is None:
            self._pool = [self.render() for _ in range(NOISE_POOL)]
        return self._pool

    def _quantise(self, image: np.ndarray) -> np.ndarray:
        np.clip(image, 0, self.full_scale, out=image)
        return np.rint(image).astype(self.dtype)

    def plate_xy(self) -> np.ndarray:
        """Fixed-frame plate ``(x, y)`` seen by each pixel centre, (H, W, 2) mm (cached).

        Inverse of :meth:`CameraSpec.project`, see :meth:`CameraSpec.unproject`.
        """
        if self._plate_xy is None:
            w, h = self.camera.resolution
            uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
            xy = self.camera.unproject(np.column_stack([uu.ravel(), vv.ravel()]))
            self._plate_xy = xy.reshape(h, w, 2)
        return self._plate_xy

    def render_chessboard(self, board: Chessboard, contrast: float = 150.0,
                          noise: bool = True) -> np.ndarray:
        """The chessboard on the plate as the camera sees it (lens distortion included).

        Squares alternate ``+-contrast/2`` around the background; a one-square quiet zone of
        the light colour surrounds the pattern. Edges are anti-aliased over about one pixel:
        per axis ``s = clip(dist_to_grid_line / pixel_in_squares, -1, 1)`` signed by the square
        parity, value ``-s_1 s_2`` (square (-1, -1) dark), so each x-corner is a saddle centred
        on the true corner.
        """
        b = board.board_coordinates(self.plate_xy())
        px = self.camera.pixel_size_mm / board.square_mm  # one pixel in squares
        s = []
        for k in range(2):
            x = b[..., k]
            frac = x - np.floor(x)
            dist = 0.5 - np.abs(frac - 0.5)  # to the nearest grid line, in squares
            parity = np.where(np.floor(x) % 2 == 0, 1.0, -1.0)
            s.append(np.clip(parity * dist / px, -1.0, 1.0))
        value = -s[0] * s[1]  # the square at board (-1, -1) is dark
        cols, rows = board.pattern
        inside = ((b[..., 0] > -1) & (b[..., 0] < cols) & (b[..., 1] > -1) & (b[..., 1] < rows))
        zone = ((b[..., 0] > -2) & (b[..., 0] < cols + 1) & (b[..., 1] > -2)
                & (b[..., 1] < rows + 1))
        image = self.base.copy()
        image += np.where(inside, value, np.where(zone, 1.0, 0.0)).astype(np.float32) * (
            contrast / 2 * self.scale)
        if noise:
            image += self._read_noise()
        return self._quantise(image)
