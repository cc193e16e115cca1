"""Scene objects the simulator renders: chessboard and ChArUco targets, a metal cylinder.

Every object has a pose ``T_camera_object`` (rotation ``R`` and translation ``t``, mm)
and answers :meth:`hit`: where rays meet it, its surface normal, diffuse albedo and
specular weight there. Geometry and texture are analytic, so the ground truth (corner
positions, mark positions) is exact.

Board frame (the detector's convention, see ``features/boards.py``): inner corners on
``z = 0``, corner ``(col, row)`` at ``(col * s, row * s, 0)``, id ``row * cols + col``.
The checker area spans ``-s <= x < cols * s``, ``-s <= y < rows * s`` (one outer square
beyond the inner corners on each side); the square whose corner nearest the origin is
``(i s, j s)`` is black when ``i + j`` is even, so the top-left outer square is black.
Around the checker area a white margin of ``margin_squares`` squares, then the card ends.

The metal cylinder may carry pits (:data:`PIT_SHAPE`): smooth depressions of known depth
along the inward normal, intersected exactly (see :class:`MetalCylinder`).

A ChArUco board is the same card with OpenCV's pattern printed on it: ``squares_x x
squares_y`` squares (so ``squares_x - 1`` by ``squares_y - 1`` inner corners, numbered as
OpenCV numbers ChArUco corners, which is the rule above), an ArUco marker in every white
square. The pattern is the image ``cv2.aruco.CharucoBoard.generateImage`` draws (current,
non-legacy layout), mapped onto the checker area.
"""

from __future__ import annotations

import dataclasses
from functools import cached_property
from typing import Any, NamedTuple

import numpy as np

__all__ = [
    "Hit",
    "Chessboard",
    "CharucoBoard",
    "MetalCylinder",
    "PIT_SHAPE",
    "target_from_preset",
]


class Hit(NamedTuple):
    """Where rays meet an object (arrays over rays, NaN/False where missed)."""

    t: np.ndarray  # (N,) mm along the unit direction, NaN where missed
    hit: np.ndarray  # (N,) bool
    normal: tuple  # 3 components (arrays (N,) or floats), unit, camera frame, facing the rays
    albedo: np.ndarray  # (N,) diffuse reflectance, 0 where missed
    specular: float  # Blinn-Phong weight, 0 for matte objects


def _pose(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    R = np.asarray(R, dtype=np.float64).reshape(3, 3)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    return R, t


class _FlatBoard:
    """Geometry shared by the flat printed boards: pose, corners, outline, ray hits.

    Subclasses provide ``cols``, ``rows`` (inner corners), ``square_mm``,
    ``margin_squares``, the pose ``R``, ``t`` and :meth:`_albedo`.
    """

    cols: int
    rows: int
    square_mm: float
    margin_squares: float
    R: np.ndarray
    t: np.ndarray

    def with_pose(self, R: np.ndarray, t: np.ndarray):
        R, t = _pose(R, t)
        return dataclasses.replace(self, R=R, t=t)

    @cached_property
    def corners_board(self) -> np.ndarray:
        """Inner corners in the board frame, shape (rows * cols, 3), mm, id order."""
        row, col = np.divmod(np.arange(self.rows * self.cols), self.cols)
        s = self.square_mm
        return np.stack([col * s, row * s, np.zeros(row.size)], axis=-1)

    @property
    def corners_camera(self) -> np.ndarray:
        """Inner corners in the camera frame, shape (rows * cols, 3), mm, id order."""
        return self.corners_board @ self.R.T + self.t

    @property
    def centre_board(self) -> np.ndarray:
        """Centre of the checker area in the board frame, mm."""
        s = self.square_mm
        return np.array([(self.cols - 1) * s / 2.0, (self.rows - 1) * s / 2.0, 0.0])

    def outline_board(self, per_side: int = 24, grow_squares: float = 0.0) -> np.ndarray:
        """Points along the outer edge of the checker area, board frame, shape (4 per_side, 3).

        ``grow_squares`` moves the outline outwards (e.g. into the white margin).
        """
        s = self.square_mm
        lo_x, hi_x = -s * (1 + grow_squares), s * (self.cols + grow_squares)
        lo_y, hi_y = -s * (1 + grow_squares), s * (self.rows + grow_squares)
        f = np.linspace(0.0, 1.0, per_side, endpoint=False)
        sides = [
            np.stack([lo_x + f * (hi_x - lo_x), np.full_like(f, lo_y)], -1),
            np.stack([np.full_like(f, hi_x), lo_y + f * (hi_y - lo_y)], -1),
            np.stack([hi_x - f * (hi_x - lo_x), np.full_like(f, hi_y)], -1),
            np.stack([np.full_like(f, lo_x), hi_y - f * (hi_y - lo_y)], -1),
        ]
        xy = np.concatenate(sides)
        return np.concatenate([xy, np.zeros((xy.shape[0], 1))], axis=-1)

    def _albedo(self, bx: np.ndarray, by: np.ndarray, dtype) -> np.ndarray:
        """Reflectance at board coordinates in squares (``x / square_mm``, ``y / square_mm``)."""
        raise NotImplementedError

    def hit(self, o: tuple[np.ndarray, ...], d: tuple[np.ndarray, ...]) -> Hit:
        """Intersect rays with the card.

        Parameters
        ----------
        o, d : tuple of 3 ndarray, shape (N,)
            Ray origin (mm) and unit direction components, camera frame.
        """
        R, t0 = self.R, self.t
        nx, ny, nz = R[:, 2]
        denom = d[0] * nx + d[1] * ny + d[2] * nz
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (R[:, 2] @ t0 - (o[0] * nx + o[1] * ny + o[2] * nz)) / denom
        t[~(t > 0)] = np.nan
        px, py, pz = (o[k] + t * d[k] - t0[k] for k in range(3))
        inv_s = 1.0 / self.square_mm
        bx = (px * R[0, 0] + py * R[1, 0] + pz * R[2, 0]) * inv_s  # (R^T (p - t))_x / s
        by = (px * R[0, 1] + py * R[1, 1] + pz * R[2, 1]) * inv_s
        m = self.margin_squares
        hit = (bx >= -1 - m) & (bx < self.cols + m) & (by >= -1 - m) & (by < self.rows + m)
        albedo = self._albedo(bx, by, t.dtype)
        albedo[~hit] = 0.0
        t[~hit] = np.nan
        flip = -1.0 if R[:, 2] @ np.array([0.0, 0.0, 1.0]) > 0 else 1.0  # face the camera
        normal = (flip * nx, flip * ny, flip * nz)
        return Hit(t, hit, normal, albedo, 0.0)


@dataclasses.dataclass(frozen=True, eq=False)
class Chessboard(_FlatBoard):
    """A flat printed chessboard on a white card.

    Attributes
    ----------
    cols, rows : int
        Inner corners per row / per column.
    square_mm : float, mm
    margin_squares : float
        White margin around the checker area, in squares.
    black, white : float
        Diffuse reflectances of the dark and light squares.
    R, t : ndarray (3, 3), (3,)
        Pose ``T_camera_board``: a board point ``p`` is at ``R p + t`` in the camera frame.
    """

    cols: int
    rows: int
    square_mm: float
    margin_squares: float
    black: float
    white: float
    R: np.ndarray
    t: np.ndarray
    name: str = "board"

    kind = "chessboard"

    @property
    def spec(self) -> str:
        """Detector spec string, e.g. ``chessboard:8x6:1``."""
        from endomeasure.features.boards import ChessboardSpec

        return ChessboardSpec(self.cols, self.rows, self.square_mm).canonical()

    def _albedo(self, bx: np.ndarray, by: np.ndarray, dtype) -> np.ndarray:
        i = np.floor(bx)
        j = np.floor(by)
        checker = (i >= -1) & (i <= self.cols - 1) & (j >= -1) & (j <= self.rows - 1)
        dark = checker & (np.mod(i + j, 2.0) == 0)
        return np.where(dark, self.black, self.white).astype(dtype)

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "name": self.name,
            "spec": self.spec,
            "cols": self.cols,
            "rows": self.rows,
            "square_mm": self.square_mm,
            "margin_squares": self.margin_squares,
            "reflectance_black": self.black,
            "reflectance_white": self.white,
        }


@dataclasses.dataclass(frozen=True, eq=False)
class CharucoBoard(_FlatBoard):
    """A flat printed OpenCV ChArUco board on a white card.

    Attributes
    ----------
    squares_x, squares_y : int
        Squares along the board's x and y (``squares_x - 1`` x ``squares_y - 1`` inner
        corners).
    square_mm, marker_mm : float, mm
        Side of a square and of an ArUco marker (with its one-bit black border).
    dictionary : str
        Predefined ArUco dictionary, e.g. ``DICT_4X4_1000``.
    texels_per_square : int
        Resolution of the pattern image drawn by OpenCV. The texture is exact (not an
        approximation of a finer pattern) when every marker bit and the white gap around
        the marker are whole texels; :meth:`from_spec` checks that.
    margin_squares, black, white, R, t, name : as :class:`Chessboard`.

    Notes
    -----
    The pattern is the image ``generateImage`` draws, ``squares_x * texels_per_square``
    wide, placed so that its top-left corner is the board's outer corner ``(-s, -s)``.
    Each ray sample reads the texel it falls in (the pattern is piecewise constant, so
    that is its exact value at the sample's point); the renderer's supersampling is the
    anti-aliasing, as for the chessboard. Texel edges are at multiples of
    ``s / texels_per_square``, so the square edges, hence the inner corners, are exactly
    where the board frame puts them.
    """

    squares_x: int
    squares_y: int
    square_mm: float
    marker_mm: float
    dictionary: str
    texels_per_square: int
    margin_squares: float
    black: float
    white: float
    R: np.ndarray
    t: np.ndarray
    name: str = "charuco"

    kind = "charuco"

    @property
    def cols(self) -> int:
        """Inner corners per row."""
        return self.board_spec.cols

    @property
    def rows(self) -> int:
        """Inner corners per column."""
        return self.board_spec.rows

    @property
    def spec(self) -> str:
        """Detector spec string, e.g. ``charuco:26x22:1.5:1.125:DICT_4X4_1000``."""
        return self.board_spec.canonical()

    @cached_property
    def board_spec(self):
        """The :class:`~endomeasure.features.boards.CharucoSpec` of this board."""
        from endomeasure.features.boards import parse_board_spec

        return parse_board_spec(
            f"charuco:{self.squares_x}x{self.squares_y}:{self.square_mm!r}:"
            f"{self.marker_mm!r}:{self.dictionary}"
        )

    @cached_property
    def pattern(self) -> np.ndarray:
        """The board as OpenCV draws it: True where black, shape (squares_y T, squares_x T)."""
        from endomeasure.features.charuco import opencv_charuco_board

        T = self.texels_per_square
        drawn = opencv_charuco_board(self.board_spec).generateImage(
            (self.squares_x * T, self.squares_y * T), marginSize=0, borderBits=1
        )
        return drawn <= 127

    def _albedo(self, bx: np.ndarray, by: np.ndarray, dtype) -> np.ndarray:
        T = self.texels_per_square
        height, width = self.pattern.shape
        with np.errstate(invalid="ignore"):
            tx = np.floor((bx + 1.0) * T)
            ty = np.floor((by + 1.0) * T)
            inside = (tx >= 0) & (tx < width) & (ty >= 0) & (ty < height)
        flat = np.where(inside, ty * width + tx, 0).astype(np.int64)
        dark = inside & self.pattern.ravel().take(flat)
        return np.where(dark, self.black, self.white).astype(dtype)

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "name": self.name,
            "spec": self.spec,
            "squares_x": self.squares_x,
            "squares_y": self.squares_y,
            "cols": self.cols,
            "rows": self.rows,
            "square_mm": self.square_mm,
            "marker_mm": self.marker_mm,
            "dictionary": self.dictionary,
            "layout": "OpenCV CharucoBoard, setLegacyPattern(False); top-left square black",
            "texels_per_square": self.texels_per_square,
            "margin_squares": self.margin_squares,
            "reflectance_black": self.black,
            "reflectance_white": self.white,
        }


def _value_noise(grid: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Smoothly interpolated lattice noise: ``grid`` sampled at fractional ``(x, y)``.

    ``grid`` is square with a power-of-two side, so coordinates wrap around it with a
    bit mask and the texture is defined everywhere.
    """
    n = grid.shape[0]
    flat = grid.ravel()
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = x - x0
    fy = y - y0
    fx = fx * fx * (3.0 - 2.0 * fx)  # smoothstep: C1 across lattice lines
    fy = fy * fy * (3.0 - 2.0 * fy)
    ix = x0.astype(np.int64) & (n - 1)
    iy = (y0.astype(np.int64) & (n - 1)) * n
    ix1 = (ix + 1) & (n - 1)
    iy1 = (iy + n) & (n * n - 1)
    top = flat.take(iy + ix)
    top += (flat.take(iy + ix1) - top) * fx
    bottom = flat.take(iy1 + ix)
    bottom += (flat.take(iy1 + ix1) - bottom) * fx
    return top + (bottom - top) * fy


# (cell along the arc, cell along the axis, weight) of the texture's noise octaves, mm:
# fine brushing streaks along the arc, then blotches of oxidation and wear.
_OCTAVES = ((0.5, 0.05, 0.35), (0.12, 0.12, 0.25), (0.4, 0.4, 0.25), (1.5, 1.5, 0.15))
_GRID = 256


PIT_SHAPE = (
    "depression along the inward normal h = depth (1 - (r / radius)^2)^2 for r < radius, 0 "
    "beyond; r the distance from the pit centre in surface coordinates (s, y); depths add "
    "where pits overlap"
)
"""The pits' shape: a bowl whose deepest point, at its centre, lies exactly ``depth``
below the cylinder, with zero slope there and at its rim (C1 into the undamaged surface)."""
PIT_COLUMNS = ("s_mm", "y_mm", "radius_mm", "depth_mm")
"""The columns of :attr:`MetalCylinder.pits` and of the preset's ``pits_mm`` rows."""
_BOWL_SLOPE = 8.0 / (3.0 * np.sqrt(3.0))
"""Largest ``|dh/dr|`` of the bowl in units of depth / radius (at ``r = radius / sqrt 3``)."""
_PIT_TOL_MM = 1e-10
"""A pit hit is converged when ``|F| <= this``; ``|grad F| >= 1``, so the point is then
within this distance of the surface."""
_PIT_NEWTON_MM = 1e-4
"""Below this ``F`` the search takes Newton steps instead of safe (Lipschitz) steps: the
Newton step is then far shorter than the bowl's radius of curvature, so it cannot jump a
fold of the surface."""
_PIT_MAX_STEPS = 500
"""Iterations of the pit intersection before a ray counts as not converged (a ray nearly
tangent to a pit wall; reported as a miss, never as a wrong point)."""


def _pit_field(pits: np.ndarray, s: np.ndarray, y: np.ndarray):
    """Depression ``h`` (mm, >= 0) of the pits and its derivatives ``dh/ds``, ``dh/dy``.

    Parameters
    ----------
    pits : ndarray, shape (P, 4), mm
        Rows ``(s, y, radius, depth)``.
    s, y : ndarray, shape (N,), mm
        Surface coordinates.
    """
    h, h_s, h_y = np.zeros(s.shape), np.zeros(s.shape), np.zeros(s.shape)
    for s0, y0, radius, depth in pits:
        near = np.flatnonzero((np.abs(s - s0) < radius) & (np.abs(y - y0) < radius))
        if near.size == 0:
            continue
        ds, dy = s[near] - s0, y[near] - y0
        w = np.clip(1.0 - (ds * ds + dy * dy) / (radius * radius), 0.0, None)
        h[near] += depth * w * w
        k = -4.0 * depth * w / (radius * radius)
        h_s[near] += k * ds
        h_y[near] += k * dy
    return h, h_s, h_y


@dataclasses.dataclass(frozen=True, eq=False)
class MetalCylinder:
    """A convex metal cylinder (e.g. a blade root or a tube) with small dark marks.

    Surface frame: the cylinder axis is parallel to y through ``(0, 0, radius)``; the
    origin is the surface point facing the camera, with outward normal ``-z``. A surface
    point with arc length ``s`` (from the origin, around the axis) and height ``y`` is
    ``(radius sin(s / radius), y, radius (1 - cos(s / radius)))``.

    Attributes
    ----------
    radius_mm : float
    albedo, texture_contrast : float
        Mean diffuse reflectance and its relative variation by the texture.
    specular, shininess : float
        Blinn-Phong weight and exponent (a brushed-metal sheen).
    texture_seed : int
        Seed of the texture lattices (fixed per object: every image shows the same part).
    marks_sy : ndarray, shape (M, 2), mm
        Arc length and height of the mark centres.
    mark_radius_mm, mark_albedo : float
    R, t : pose ``T_camera_surface``.
    pits : ndarray, shape (P, 4), mm
        Pits (:data:`PIT_SHAPE`), rows ``(s, y, radius, depth)``: centre, radius and the
        depth of the deepest point below the cylinder; default none. The texture keeps
        following ``(s, y)`` into a pit.

    Notes
    -----
    With pits the surface is, in cylindrical coordinates about the axis, the radius
    ``rho = radius_mm - h(s, y)`` with ``s = radius_mm * phi``; ``F(p) = rho(p) -
    radius_mm + h(s(p), y(p))`` is zero on it, positive outside (in the air) and
    ``|grad F| >= 1``. A ray first meets the cylinder at ``t_c``; where ``h`` is zero
    there, that is its hit, exactly the plain cylinder's. Otherwise it entered a pit's
    mouth and the hit is the first root of ``F(o + t d)`` beyond ``t_c``: safe steps
    ``t += F / L`` (sphere tracing; ``L`` bounds ``|grad F|`` wherever ``F >= 0``, so a
    step never passes the first root), Newton steps once ``F`` is below
    :data:`_PIT_NEWTON_MM`, kept inside the bracket ``F > 0 > F`` once one is known (else
    bisection), until ``|F| <= ``:data:`_PIT_TOL_MM`, in float64 whatever the rays'
    precision. A ray that leaves through the pit's mouth again misses the part. The normal
    is ``grad F / |grad F|`` at the hit (the pit wall's, for the shading).
    """

    radius_mm: float
    albedo: float
    texture_contrast: float
    specular: float
    shininess: float
    texture_seed: int
    marks_sy: np.ndarray
    mark_radius_mm: float
    mark_albedo: float
    R: np.ndarray
    t: np.ndarray
    name: str = "metal"
    pits: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 4)))

    kind = "cylinder"

    def __post_init__(self):
        pits = np.asarray(self.pits, dtype=np.float64).reshape(-1, 4)
        if not np.all(np.isfinite(pits)) or np.any(pits[:, 2:] <= 0):
            raise ValueError(f"target {self.name!r}: pits need a finite, positive radius and depth")
        if pits[:, 3].sum() >= self.radius_mm:
            raise ValueError(f"target {self.name!r}: the pits' depths reach the cylinder's axis")
        object.__setattr__(self, "pits", pits)

    def with_pose(self, R: np.ndarray, t: np.ndarray) -> MetalCylinder:
        R, t = _pose(R, t)
        return dataclasses.replace(self, R=R, t=t)

    def with_pits(self, pits: np.ndarray) -> MetalCylinder:
        """The same part with these pits (P, 4) ``(s, y, radius, depth)``, mm, instead."""
        return dataclasses.replace(self, pits=pits)

    @cached_property
    def _lattices(self) -> list[np.ndarray]:
        rng = np.random.default_rng(self.texture_seed)
        return [rng.uniform(-1.0, 1.0, size=(_GRID, _GRID)).astype(np.float32) for _ in _OCTAVES]

    def surface_points(self, s: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Surface-frame points of arc length ``s`` and height ``y``, shape (..., 3), mm."""
        phi = np.asarray(s, dtype=np.float64) / self.radius_mm
        return np.stack(
            [self.radius_mm * np.sin(phi), np.asarray(y, dtype=np.float64) + 0 * phi,
             self.radius_mm * (1.0 - np.cos(phi))], axis=-1,
        )  # fmt: skip

    @property
    def marks_surface(self) -> np.ndarray:
        """Mark centres in the surface frame, shape (M, 3), mm."""
        return self.surface_points(self.marks_sy[:, 0], self.marks_sy[:, 1])

    @property
    def marks_camera(self) -> np.ndarray:
        """Mark centres in the camera frame, shape (M, 3), mm."""
        return self.marks_surface @ self.R.T + self.t

    @property
    def pit_bottoms_camera(self) -> np.ndarray:
        """Each pit's deepest point (its centre, ``depth`` below the cylinder along the
        inward normal) in the camera frame, shape (P, 3), mm; of a lone pit (overlapping
        pits add their depths)."""
        s, y, _, depth = self.pits.T
        phi = s / self.radius_mm
        rho = self.radius_mm - depth
        bottom = np.stack([rho * np.sin(phi), y, self.radius_mm - rho * np.cos(phi)], axis=-1)
        return bottom @ self.R.T + self.t

    def texture(self, s: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Diffuse albedo at surface coordinates (arc length, height), mm."""
        noise = np.zeros(np.shape(s), dtype=np.result_type(s, np.float32))
        for (cell_s, cell_y, weight), grid in zip(_OCTAVES, self._lattices, strict=True):
            noise += weight * _value_noise(grid, s / cell_s, y / cell_y)
        albedo = self.albedo * (1.0 + self.texture_contrast * noise)
        # marks: dark discs with a soft rim (anti-aliasing is the renderer's job; the rim
        # is the physical edge of a punched or etched mark)
        reach = self.mark_radius_mm * 1.2
        for ms, my in self.marks_sy:
            near = np.flatnonzero((np.abs(s - ms) < reach) & (np.abs(y - my) < reach))
            if near.size == 0:
                continue
            r = np.hypot(s[near] - ms, y[near] - my)
            edge = np.clip((r - self.mark_radius_mm) / (0.15 * self.mark_radius_mm) + 0.5, 0, 1)
            albedo[near] = self.mark_albedo + (albedo[near] - self.mark_albedo) * edge
        return albedo

    def hit(self, o: tuple[np.ndarray, ...], d: tuple[np.ndarray, ...]) -> Hit:
        """Intersect rays (component tuples, camera frame) with the cylinder's front side."""
        R, t0 = self.R, self.t
        rel = [o[k] - t0[k] for k in range(3)]
        # to the surface frame: R^T v
        lo = [rel[0] * R[0, k] + rel[1] * R[1, k] + rel[2] * R[2, k] for k in range(3)]
        ld = [d[0] * R[0, k] + d[1] * R[1, k] + d[2] * R[2, k] for k in range(3)]
        r0 = self.radius_mm
        oz = lo[2] - r0
        a = ld[0] ** 2 + ld[2] ** 2
        b = 2.0 * (lo[0] * ld[0] + oz * ld[2])
        c = lo[0] ** 2 + oz**2 - r0 * r0
        disc = b * b - 4.0 * a * c
        with np.errstate(invalid="ignore", divide="ignore"):
            t = (-b - np.sqrt(disc)) / (2.0 * a)
        hit = (disc > 0) & (t > 0)
        t[~hit] = np.nan
        pitted = None
        if len(self.pits):
            with np.errstate(invalid="ignore", divide="ignore"):
                t_back = (-b + np.sqrt(disc)) / (2.0 * a)
            pitted, grad = self._pit_hits(lo, ld, t, hit, t_back)
        sx, sy, sz = (lo[k] + t * ld[k] for k in range(3))
        s_arc = r0 * np.arctan2(sx, r0 - sz)
        albedo = np.zeros_like(t)
        albedo[hit] = self.texture(s_arc[hit], sy[hit])
        # outward normal (x, 0, z - r) / r in the surface frame, to the camera frame
        ux, uz = sx / r0, (sz - r0) / r0
        if pitted is not None and pitted.size:
            ux, uz = np.array(ux, copy=True), np.array(uz, copy=True)
            uy = np.zeros_like(ux)
            norm = np.sqrt(grad[0] ** 2 + grad[1] ** 2 + grad[2] ** 2)
            ux[pitted], uy[pitted], uz[pitted] = (g / norm for g in grad)
            normal = tuple(ux * R[k, 0] + uy * R[k, 1] + uz * R[k, 2] for k in range(3))
        else:
            normal = tuple(ux * R[k, 0] + uz * R[k, 2] for k in range(3))
        return Hit(t, hit, normal, albedo, self.specular)

    def _surface_function(self, o: np.ndarray, d: np.ndarray, t: np.ndarray):
        """``F``, ``dF/dt`` and ``grad F`` (3 arrays) at ``o + t d`` (surface frame, (3, n))."""
        r0 = self.radius_mm
        x, y, zc = o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2] - r0
        rho = np.hypot(x, zc)
        h, h_s, h_y = _pit_field(self.pits, r0 * np.arctan2(x, -zc), y)
        # grad F = e_rho + h_s (r0 / rho) e_phi + h_y e_y; e_rho = (x, 0, zc) / rho and
        # e_phi = (-zc, 0, x) / rho (the direction of growing s)
        k = h_s * r0 / rho
        grad = ((x - k * zc) / rho, h_y, (zc + k * x) / rho)
        slope = grad[0] * d[0] + grad[1] * d[1] + grad[2] * d[2]
        return rho - r0 + h, slope, grad

    def _pit_hits(self, lo, ld, t: np.ndarray, hit: np.ndarray, t_back: np.ndarray):
        """Move ``t`` (in place) of the rays that enter a pit's mouth to the pit's surface.

        Returns the indices of those rays and ``grad F`` (3 arrays) at their hits; a ray
        that leaves through the mouth again, or does not converge, becomes a miss.
        """
        r0 = self.radius_mm
        idx = np.flatnonzero(hit)
        o = np.stack([np.asarray(lo[k], dtype=np.float64)[idx] for k in range(3)])
        d = np.stack([np.asarray(ld[k], dtype=np.float64)[idx] for k in range(3)])
        t0 = t[idx].astype(np.float64)
        x, y, z = o + t0 * d
        inside = _pit_field(self.pits, r0 * np.arctan2(x, r0 - z), y)[0] > 0
        idx, o, d, tt = idx[inside], o[:, inside], d[:, inside], t0[inside]
        t_end = np.asarray(t_back, dtype=np.float64)[idx]
        # |grad F|^2 = 1 + (h_s r0 / rho)^2 + h_y^2 and rho >= r0 - sum(depth) where F >= 0
        depth_sum = float(self.pits[:, 3].sum())
        max_slope = float(np.sum(_BOWL_SLOPE * self.pits[:, 3] / self.pits[:, 2]))
        lipschitz = float(np.hypot(1.0, max_slope * r0 / (r0 - depth_sum)))
        F, slope, grad = self._surface_function(o, d, tt)
        t_lo, F_lo = tt.copy(), F.copy()  # F > 0 here: at or before the first root
        t_hi = np.full(tt.shape, np.inf)  # F < 0 here, once known
        done = np.abs(F) <= _PIT_TOL_MM
        left = np.zeros(tt.shape, dtype=bool)  # left through the mouth: a miss
        for _ in range(_PIT_MAX_STEPS):
            act = np.flatnonzero(~done)
            if act.size == 0:
                break
            newton = (np.abs(F[act]) <= _PIT_NEWTON_MM) & (slope[act] < 0)
            with np.errstate(divide="ignore", invalid="ignore"):
                step = np.where(newton, tt[act] - F[act] / slope[act],
                                t_lo[act] + F_lo[act] / lipschitz)  # fmt: skip
            lo_a, hi_a = t_lo[act], t_hi[act]
            outside = np.isfinite(hi_a) & ~((step > lo_a) & (step < hi_a))
            step = np.where(outside, 0.5 * (lo_a + hi_a), step)
            f, s, g = self._surface_function(o[:, act], d[:, act], step)
            tt[act], F[act], slope[act] = step, f, s
            for k in range(3):
                grad[k][act] = g[k]
            above = f > 0
            t_lo[act] = np.where(above, step, lo_a)
            F_lo[act] = np.where(above, f, F_lo[act])
            t_hi[act] = np.where(above, hi_a, step)
            gone = above & (step > t_end[act])
            left[act] = gone
            done[act] = (np.abs(f) <= _PIT_TOL_MM) | gone
        missed = ~done | left
        t[idx] = np.where(missed, np.nan, tt)
        hit[idx[missed]] = False
        keep = ~missed
        return idx[keep], tuple(g[keep] for g in grad)

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "name": self.name,
            "radius_mm": self.radius_mm,
            "surface_frame": (
                "cylinder axis parallel to y through (0, 0, radius); origin on the surface "
                "facing the camera; point(s, y) = (r sin(s/r), y, r (1 - cos(s/r)))"
            ),
            "albedo": self.albedo,
            "texture_contrast": self.texture_contrast,
            "specular": self.specular,
            "shininess": self.shininess,
            "texture_seed": self.texture_seed,
            "mark_radius_mm": self.mark_radius_mm,
            **(
                {
                    "pits_mm": self.pits.tolist(),
                    "pit_columns": list(PIT_COLUMNS),
                    "pit_shape": PIT_SHAPE,
                }
                if len(self.pits)
                else {}
            ),  # fmt: skip
        }


def _marker_bits(dictionary: str) -> int:
    """Bits per side of a predefined ArUco dictionary's markers (without the border)."""
    return 5 if dictionary == "DICT_ARUCO_ORIGINAL" else int(dictionary[5])


def _check_texels(board: CharucoBoard) -> None:
    """Refuse a texel size at which OpenCV would round the markers' cells or gap.

    Raises
    ------
    ValueError
        The marker (``marker_mm / square_mm * T`` texels), its gap to the square's edge
        and its cells (the bits plus a one-bit border on each side) are not whole texels.
    """
    from endomeasure.errors import BadInputError

    try:
        board.board_spec  # noqa: B018 - validates squares, marker, dictionary
    except BadInputError as exc:
        raise ValueError(f"target {board.name!r}: {exc.what}") from None
    T = board.texels_per_square
    marker = board.marker_mm / board.square_mm * T
    cells = _marker_bits(board.dictionary) + 2
    whole = round(marker)
    if T < 1 or abs(marker - whole) > 1e-9 or (T - whole) % 2 or whole % cells:
        raise ValueError(
            f"target {board.name!r}: at {T} texels per square the marker is {marker:g} texels; "
            f"choose texels_per_square so that it is a whole multiple of {cells} (the marker's "
            "cells) with an even number of texels left over (the gap on both sides)"
        )


def target_from_preset(name: str, spec: dict[str, Any]):
    """Build an (unposed) target from its preset entry."""
    kind = spec.get("kind")
    eye, zero = np.eye(3), np.zeros(3)
    if kind == "chessboard":
        return Chessboard(
            int(spec["cols"]), int(spec["rows"]), float(spec["square_mm"]),
            float(spec.get("margin_squares", 1.0)), float(spec.get("black", 0.06)),
            float(spec.get("white", 0.85)), eye, zero, name,
        )  # fmt: skip
    if kind == "charuco":
        board = CharucoBoard(
            squares_x=int(spec["squares_x"]), squares_y=int(spec["squares_y"]),
            square_mm=float(spec["square_mm"]), marker_mm=float(spec["marker_mm"]),
            dictionary=str(spec["dictionary"]),
            texels_per_square=int(spec["texels_per_square"]),
            margin_squares=float(spec.get("margin_squares", 1.0)),
            black=float(spec.get("black", 0.06)), white=float(spec.get("white", 0.85)),
            R=eye, t=zero, name=name,
        )  # fmt: skip
        _check_texels(board)
        return board
    if kind == "cylinder":
        return MetalCylinder(
            float(spec["radius_mm"]), float(spec["albedo"]), float(spec["texture_contrast"]),
            float(spec["specular"]), float(spec["shininess"]), int(spec["texture_seed"]),
            np.asarray(spec["marks_mm"], dtype=np.float64).reshape(-1, 2),
            float(spec["mark_radius_mm"]), float(spec["mark_albedo"]), eye, zero, name,
            np.asarray(spec.get("pits_mm", []), dtype=np.float64).reshape(-1, 4),
        )  # fmt: skip
    raise ValueError(f"target {name!r} has unknown kind {kind!r}")
