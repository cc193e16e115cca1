"""A design space of forward-view biprism probes: whole presets drawn at random.

:func:`draw_design` turns a seed into a complete preset document (the format of
``presets/default.json``) of a plausible probe: sensor, lens (distortion defined either
way, tangential terms, off-centre principal point, a pupil moving with field), biprism
(glass, unequal wedges, tilted rear face, off-axis tilted apex line, face offsets),
illumination, three chessboards and the paper's protocol, all scaled to the drawn
optics. Designs that are not physical (total internal reflection inside the field, a lens
map that folds inside the image, a split band outside the image, halves without enough
common field for the boards) are redrawn from a deterministic sub-seed, so the result is
a pure function of the seed. Every range, and where it comes from: ``docs/simulator.md``,
"Design space".
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np

from endomeasure.conventions import Half, Status
from endomeasure.simulate.preset import PRESET_FORMAT, PRESET_VERSION, Preset
from endomeasure.simulate.scenes import APEX_CLEARANCE_SIGMAS, BORDER_CLEARANCE_PX
from endomeasure.simulate.truth_optics import LensMap, TruthOptics

__all__ = [
    "DESIGN_RANGES_VERSION",
    "RANGES",
    "GLASSES",
    "SENSOR_FORMATS",
    "draw_design",
    "common_field",
    "check_optics",
    "DesignError",
]

DESIGN_RANGES_VERSION = 1

SENSOR_FORMATS = {
    "4:3": ((320, 240), (400, 300), (640, 480), (800, 600), (1024, 768), (1280, 960), (1600, 1200)),
    "16:10": ((640, 400), (1280, 800), (1440, 900)),
    "5:4": ((640, 512), (1280, 1024)),
}
ASPECT_WEIGHTS = {"4:3": 0.7, "16:10": 0.15, "5:4": 0.15}

GLASSES = (
    ("fused silica", 1.4585), ("N-FK5", 1.4875), ("N-BK7", 1.5168), ("N-K5", 1.5224),
    ("N-BAK4", 1.5688), ("N-SK16", 1.6204), ("N-F2", 1.6200), ("N-SF5", 1.6727),
    ("N-SF11", 1.7847), ("N-SF57", 1.8467), ("N-LASF9", 1.8503), ("N-SF66", 1.9229),
)  # fmt: skip
"""Prism glasses and their index at the helium d-line (Schott / Heraeus catalogues)."""

RANGES: dict[str, Any] = {
    "sensor_width_mm": (1.8, 5.4),
    "pixel_pitch_um": (1.4, 8.0),
    "full_field_deg": (80.0, 140.0),
    "corner_distortion": (0.0, 0.35),
    "tangential": (-5e-4, 5e-4),
    "principal_offset_fraction": 0.03,
    "principal_offset_max_px": 40.0,
    "fy_over_fx": (0.995, 1.005),
    "pupil_shift_mm": (0.0, 0.1),
    "wedge_deg": (15.0, 45.0),
    "deviation_fraction": (0.85, 1.15),
    "wedge_asymmetry_deg": 3.0,
    "front_b_deg": 0.5,
    "rear_tilt_deg": 1.0,
    "rear_distance_mm": (0.3, 1.5),
    "thickness_mm": (0.8, 3.0),
    "apex_offset_fraction": 0.08,
    "apex_y_mm": 0.05,
    "face_offset_mm": 0.02,
    "near_over_convergence": (4.0, 7.0),
    "far_over_near": (3.5, 5.0),
    "f_number": (4.0, 8.0),
    "psf_sigma_px": (0.45, 0.7),
    "max_defocus_px": 3.0,
    "max_f_number": 16.0,
    "vignetting_exponent": (1.0, 2.0),
    "apex_band_depth": (0.85, 0.97),
    "read_noise_e": (8.0, 15.0),
}
"""The documented ranges of :func:`draw_design` (uniform unless docs say otherwise)."""

MIN_SQUARE_PX = 9.0
"""A board's squares are at least this many px wide at the far end of its distances ..."""
BLUR_SQUARE_SIGMAS = 4.5
"""... or this many PSF sigmas (at the ends of the working range), if more."""
BOARD_FILL = 0.7
"""A board's checker area spans at most this fraction of the common field at its near end."""
RANGE_RATIO = 1.4
"""The small board's squares are this many times ``MIN_SQUARE_PX`` at the near end, so
its range spans at least this ratio of distances."""
MAX_DARK_FRACTION = 0.02
"""TIR and rays missing a face may darken at most this fraction of the image, and nothing
of its centre (the middle half of the rows and 60 % of the columns)."""
MAX_ATTEMPTS = 200
_LENS_TRIES = 50
SENSOR_ATTEMPTS = 40
_GRID = (64, 48)  # pixels per axis checked for TIR and lens folding
_BOARDS = (("board_s", 8, 6), ("board_m", 6, 5), ("board_l", 6, 5))


class DesignError(ValueError):
    """A drawn design is not physical (the reason says why); the caller redraws."""


def _u(rng, lo_hi) -> float:
    lo, hi = lo_hi
    return float(rng.uniform(lo, hi))


def _sensor(rng) -> dict[str, Any]:
    names = list(ASPECT_WEIGHTS)
    aspect = names[rng.choice(len(names), p=[ASPECT_WEIGHTS[n] for n in names])]
    formats = SENSOR_FORMATS[aspect]
    width, height = formats[rng.integers(len(formats))]
    pitch = float(
        np.clip(_u(rng, RANGES["sensor_width_mm"]) / width * 1e3, *RANGES["pixel_pitch_um"])
    )
    return {
        "image_size": [int(width), int(height)],
        "pixel_pitch_um": round(pitch, 3),
        "full_well_e": round(6000.0 * (pitch / 3.75) ** 2, 1),
        "read_noise_e": round(_u(rng, RANGES["read_noise_e"]), 2),
        "black_level_dn": 3.0,
        "exposure_target": 0.75,
        "exposure_percentile": 99.0,
    }


def _profile(rng) -> np.ndarray:
    """Weights of r^2, r^4, r^6, r^8 in the distortion at the corner (sum 1, r^2 leading)."""
    w = np.array([rng.uniform(0.6, 1.0), *rng.uniform(-0.25, 0.25, 3)])
    w[1:] *= (1.0 - w[0]) / max(abs(w[1:].sum()), 1e-3) if abs(w[1:].sum()) > 1e-3 else 0.0
    w[0] = 1.0 - w[1:].sum()
    return w


def _lens(rng, width: int, height: int) -> dict[str, Any]:
    """The lens: field across the width, corner distortion, direction, pupil law."""
    half_h = np.radians(_u(rng, RANGES["full_field_deg"])) / 2.0
    big_d = _u(rng, RANGES["corner_distortion"])
    direction = "ray_to_pixel" if rng.uniform() < 0.5 else "pixel_to_ray"
    w = _profile(rng)
    a = (width / 2.0) / np.hypot(width / 2.0, height / 2.0)  # edge / corner radius ratio
    powers = np.arange(1, 5)
    if direction == "ray_to_pixel":
        # r_d = r (1 - D sum w_i rho^2i), rho = r / r_corner; the edge ideal radius tan(half_h)
        def edge_ratio(rc):
            rho = np.tan(half_h) / rc
            return np.tan(half_h) * (1 - big_d * (w @ rho ** (2 * powers))) - a * rc * (1 - big_d)

        lo, hi = np.tan(half_h), np.tan(half_h) / a * 2.0
        for _ in range(100):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if edge_ratio(mid) > 0 else (lo, mid)
        r_corner = 0.5 * (lo + hi)
        rd_corner = r_corner * (1 - big_d)
        k = -big_d * w / r_corner ** (2 * powers)
        theta_corner = np.arctan(r_corner)
        reach = r_corner  # the input radius of the map at the corner
    else:
        # r = r_d (1 + D' sum w_i rho_d^2i), D' = D / (1 - D): r_d / r = 1 - D at the corner
        dp = big_d / (1.0 - big_d)
        rd_corner = np.tan(half_h) / (a * (1.0 + dp * (w @ a ** (2 * powers))))
        k = dp * w / rd_corner ** (2 * powers)
        theta_corner = np.arctan(rd_corner * (1.0 + dp))
        reach = rd_corner
    # the lens map must be one-to-one a little beyond the corner (its input radius there)
    # (the principal point's offset moves the farthest corner out by up to 5 %)
    if LensMap(tuple(float(v) for v in k), 0.0, 0.0).max_radius < 1.1 * reach:
        raise DesignError("the drawn distortion folds inside the image")
    fx = float(np.hypot(width / 2.0, height / 2.0) / rd_corner)
    off = min(RANGES["principal_offset_fraction"] * width, RANGES["principal_offset_max_px"])
    return {
        "fx": round(fx, 4),
        "fy": round(fx * _u(rng, RANGES["fy_over_fx"]), 4),
        "cx": round((width - 1) / 2.0 + rng.uniform(-1, 1) * off, 3),
        "cy": round((height - 1) / 2.0 + rng.uniform(-1, 1) * off * height / width, 3),
        "distortion_direction": direction,
        **{f"k{i + 1}": float(k[i]) for i in range(4)},
        "p1": _u(rng, RANGES["tangential"]),
        "p2": _u(rng, RANGES["tangential"]),
        "pupil_shift_mm": round(_u(rng, RANGES["pupil_shift_mm"]), 4),
        "pupil_edge_deg": round(float(np.degrees(theta_corner)), 3),
        "f_number": round(_u(rng, RANGES["f_number"]), 2),
        "psf_sigma_px": round(_u(rng, RANGES["psf_sigma_px"]), 3),
        "vignetting_exponent": round(_u(rng, RANGES["vignetting_exponent"]), 3),
        "_full_field_deg": float(np.degrees(2 * half_h)),
        "_corner_distortion": big_d,
    }


def _wedge_limit(n: float, vertical_half_rad: float) -> float:
    """Largest wedge (rad) whose front face passes the apex column's top ray without TIR:
    ``cos(inc) = cos(a) cos(phi_in)`` with ``phi_in`` the refracted vertical angle."""
    phi_in = np.arcsin(np.sin(vertical_half_rad) / n)
    c = np.cos(np.arcsin(1.0 / n)) / np.cos(phi_in)
    return float(np.arccos(min(1.0, c)))


def _wedge_for_deviation(n: float, deviation: float) -> float:
    """Wedge angle (rad) whose centre ray, normal to the rear face, leaves deviated by
    ``deviation`` (rad): ``asin(n sin a) - a = deviation`` (solved by bisection)."""
    lo, hi = 0.0, float(np.arcsin(1.0 / n))
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if np.arcsin(n * np.sin(mid)) - mid < deviation else (lo, mid)
    return 0.5 * (lo + hi)


def _prism(rng, lens: dict[str, Any], width: int, height: int) -> dict[str, Any]:
    """The biprism: the wedge deviates each half's view by a fraction of the half field
    (a quarter of the full field overlaps the halves best), kept clear of TIR."""
    name, n = GLASSES[rng.integers(len(GLASSES))]
    vertical = np.arctan(height / 2.0 / lens["fy"])  # distorted: a lower bound of the field
    lo, hi = RANGES["wedge_deg"]
    limit = min(hi, np.degrees(_wedge_limit(n, vertical)))
    deviation = np.radians(lens["_full_field_deg"]) / 4.0 * _u(rng, RANGES["deviation_fraction"])
    wedge = min(np.degrees(_wedge_for_deviation(n, deviation)), limit - rng.uniform(0.0, 2.0))
    if not lo <= wedge <= hi:
        raise DesignError(f"glass {name}: the wedge {wedge:.1f} deg is outside {lo}-{hi} deg")
    asym = RANGES["wedge_asymmetry_deg"]
    a_left = -(wedge + rng.uniform(-asym, asym))
    a_right = wedge + rng.uniform(-asym, asym)
    if not (lo <= -a_left <= hi and lo <= a_right <= hi):
        raise DesignError(f"a wedge ({-a_left:.1f}, {a_right:.1f} deg) is outside {lo}-{hi} deg")
    rear_d = _u(rng, RANGES["rear_distance_mm"])
    apex_z = rear_d + _u(rng, RANGES["thickness_mm"])
    apex_x = rng.uniform(-1, 1) * RANGES["apex_offset_fraction"] * width / lens["fx"] * apex_z
    tilt, fb, off = RANGES["rear_tilt_deg"], RANGES["front_b_deg"], RANGES["face_offset_mm"]
    return {
        "glass": name,
        "n_glass": n,
        "rear_face": {
            "a_deg": round(rng.uniform(-tilt, tilt), 4),
            "b_deg": round(rng.uniform(-tilt, tilt), 4),
            "d_mm": round(rear_d, 4),
        },
        "left_face": {
            "a_deg": round(a_left, 4),
            "b_deg": round(rng.uniform(-fb, fb), 4),
            "offset_mm": round(rng.uniform(-off, off), 5),
        },
        "right_face": {
            "a_deg": round(a_right, 4),
            "b_deg": round(rng.uniform(-fb, fb), 4),
            "offset_mm": round(rng.uniform(-off, off), 5),
        },
        "apex_mm": [
            round(apex_x, 5),
            round(rng.uniform(-1, 1) * RANGES["apex_y_mm"], 5),
            round(apex_z, 4),
        ],
        "apex_band_depth": round(_u(rng, RANGES["apex_band_depth"]), 3),
    }


def check_optics(optics: TruthOptics) -> None:
    """Raise :class:`DesignError` where the optics are not physical over the image: total
    internal reflection or a missed face (over more than ``MAX_DARK_FRACTION`` of it, or
    anywhere in its centre), a lens map that does not invert, an apex band outside the
    middle 60 % of the width."""
    width, height = optics.config.image_size
    uu, vv = np.meshgrid(np.linspace(0, width - 1, _GRID[0]), np.linspace(0, height - 1, _GRID[1]))
    q = np.stack([uu.ravel(), vv.ravel()], -1)
    status = np.full(q.shape[0], 255)
    for half in Half:
        st = optics.rays(q, half).status
        status = np.where(st != Status.OUTSIDE_HALF, st, status)
    # TIR and rays leaving through the prism's side (a face missed) darken the image
    dark = (status == Status.TOTAL_INTERNAL_REFLECTION) | (status == Status.BEHIND)
    central = (np.abs(q[:, 1] - height / 2) < height / 4) & (
        np.abs(q[:, 0] - width / 2) < 0.3 * width
    )
    if dark.mean() > MAX_DARK_FRACTION or (dark & central).any():
        raise DesignError(
            f"total internal reflection or a missed face in {dark.mean():.1%} of the image"
        )
    if np.any((status != Status.OK) & ~dark):
        raise DesignError("the lens map does not invert inside the image")
    cols = optics.apex_columns(np.linspace(0, height - 1, 9))
    if not np.all(np.isfinite(cols)) or cols.min() < 0.2 * width or cols.max() > 0.8 * width:
        raise DesignError("the apex band leaves the middle 60 % of the image width")


_APEX_ROWS = 9  # rows at which the apex image is solved for the common field


def _apex(optics: TruthOptics) -> np.ndarray:
    """The apex image's column at ``_APEX_ROWS`` rows, computed once per optics object."""
    key = id(optics)
    if _APEX_MEMO.get(key, (None,))[0] is not optics:
        _APEX_MEMO.clear()
        rows = np.linspace(0, optics.config.image_size[1] - 1, _APEX_ROWS)
        _APEX_MEMO[key] = (optics, optics.apex_columns(rows))
    return _APEX_MEMO[key][1]


_APEX_MEMO: dict[int, tuple] = {}


def _half_outline(optics: TruthOptics, half: Half, z: float, margin_px: float, apex) -> np.ndarray:
    """Where the outline of a half's usable pixels (``margin_px`` inside the image border
    and away from the apex image) meets the plane at depth z: a polygon (K, 2), mm."""
    width, height = optics.config.image_size
    rows = np.linspace(0, height - 1, _APEX_ROWS)
    v = np.linspace(margin_px, height - 1 - margin_px, 60)
    u_apex = np.interp(v, rows, apex)
    if half is Half.LEFT:
        inner, outer = u_apex - margin_px, np.full_like(v, margin_px)
    else:
        inner, outer = u_apex + margin_px, np.full_like(v, width - 1 - margin_px)
    f = np.linspace(0.0, 1.0, 40)
    top = np.stack([outer[0] + f * (inner[0] - outer[0]), np.full_like(f, v[0])], -1)
    side = np.stack([inner, v], -1)
    bottom = np.stack([inner[-1] + f * (outer[-1] - inner[-1]), np.full_like(f, v[-1])], -1)
    back = np.stack([outer[::-1], v[::-1]], -1)
    q = np.concatenate([top, side, bottom, back])
    r = optics.rays(q, half)
    ok = (r.status == Status.OK) & (r.directions[:, 2] > 0)
    s = (z - r.origins[ok, 2]) / r.directions[ok, 2]
    return r.origins[ok, :2] + s[:, None] * r.directions[ok, :2]


def _inside(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Point-in-polygon by the crossing number, points (N, 2), polygon (K, 2)."""
    x, y = points[:, 0:1], points[:, 1:2]
    a, b = polygon, np.roll(polygon, -1, axis=0)
    spans = (a[:, 1] > y) != (b[:, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        cross = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
    return (np.sum(spans & (x < cross), axis=1) % 2) == 1


def common_field(optics: TruthOptics, z: float, margin_px: float = 4.0) -> dict[str, float]:
    """The region of the plane at depth ``z`` (mm) both halves see, clear of the borders
    and of ``margin_px`` around the apex image: its centre, width and height along the
    lines through the centre, mm, and its scale (px per mm: the smallest of both halves
    at the centre and at 35 % of the smaller of width and height out from it)."""
    apex = _apex(optics)
    outlines = [_half_outline(optics, half, z, margin_px, apex) for half in Half]
    if min(len(o) for o in outlines) < 10:
        raise DesignError(f"a half's outline does not reach the plane at {z:.1f} mm")
    lo = np.maximum(outlines[0].min(axis=0), outlines[1].min(axis=0))
    hi = np.minimum(outlines[0].max(axis=0), outlines[1].max(axis=0))
    if not np.all(hi > lo):
        raise DesignError(f"the halves see nothing in common at {z:.1f} mm")
    xs = np.linspace(lo[0], hi[0], 81)
    ys = np.linspace(lo[1], hi[1], 81)
    gx, gy = np.meshgrid(xs, ys)
    grid = np.stack([gx.ravel(), gy.ravel()], -1)
    seen = (_inside(grid, outlines[0]) & _inside(grid, outlines[1])).reshape(gx.shape)
    if seen.sum() < 4:
        raise DesignError(f"the halves see nothing in common at {z:.1f} mm")
    iy, ix = np.nonzero(seen)
    cy, cx = int(np.round(np.median(iy))), int(np.round(np.median(ix)))
    xc, yc = float(xs[cx]), float(ys[cy])
    w = float(seen[cy].sum() * (xs[1] - xs[0]))
    h = float(seen[:, cx].sum() * (ys[1] - ys[0]))
    # the local scale (px per mm) at the centre and out to a board's edge, the smallest
    reach = 0.35 * min(w, h)
    spots = [(0.0, 0.0)] + [(sx * reach, sy * reach) for sx in (-1, 1) for sy in (-1, 1)]
    d = np.array([[-0.5, 0.0], [0.5, 0.0], [0.0, -0.5], [0.0, 0.5]])
    probe = np.array([[xc + dx + a, yc + dy + b, z] for dx, dy in spots for a, b in d])
    scale = np.inf
    for half in Half:
        q = optics.project(probe, half).pixels.reshape(len(spots), 4, 2)
        steps = np.linalg.norm(q[:, [1, 3]] - q[:, [0, 2]], axis=-1)
        scale = min(scale, float(np.min(steps)) if np.all(np.isfinite(steps)) else np.nan)
    if not np.isfinite(scale):
        raise DesignError(f"the common field's centre at {z:.1f} mm is not seen in both halves")
    return {"x_mm": xc, "y_mm": yc, "width_mm": w, "height_mm": h, "px_per_mm": float(scale)}


def _baseline(optics: TruthOptics) -> float:
    """Distance between the halves' virtual viewpoints (points nearest their rays), mm."""
    width, height = optics.config.image_size
    centres = []
    for half in Half:
        lo, hi = (
            (0, optics.config.split - 1) if half is Half.LEFT else (optics.config.split, width - 1)
        )
        q = np.stack(
            np.meshgrid(np.linspace(lo, hi, 12), np.linspace(0, height - 1, 9)), -1
        ).reshape(-1, 2)
        r = optics.rays(q, half)
        ok = r.status == Status.OK
        o, d = r.origins[ok], r.directions[ok]
        P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
        centres.append(np.linalg.solve(P.sum(0), np.einsum("nij,nj->i", P, o)))
    return float(np.linalg.norm(centres[1] - centres[0]))


def _convergence(optics: TruthOptics, baseline: float) -> float:
    """Distance (mm) where the halves' views begin to overlap: the common width grows as
    ``w = a z - c`` far out, so ``z0 = c / a`` (from two distances many baselines out)."""
    z1, z2 = 20.0 * baseline, 40.0 * baseline
    w1, w2 = (common_field(optics, z)["width_mm"] for z in (z1, z2))
    a = (w2 - w1) / (z2 - z1)
    if not a > 0:
        raise DesignError("the halves' common field does not grow with distance")
    return float(max(baseline, (a * z1 - w1) / a))


def _round2(x: float, how: str = "nearest") -> float:
    """Two significant digits (board squares as a printer would make them)."""
    e = 10.0 ** (np.floor(np.log10(x)) - 1)
    rounding = {"nearest": np.round, "up": np.ceil, "down": np.floor}[how]
    return round(float(rounding(x / e) * e), 12)


def _fit_distance(cfs: list[dict], zs: np.ndarray, board: tuple, square: float) -> float:
    """Distance (mm) from which the board's checker area fits ``BOARD_FILL`` of the common
    field (interpolated; inf if it never fits within the sampled distances)."""
    _, cols, rows = board
    room = np.array([
        min(BOARD_FILL * cf["width_mm"] / (cols + 1), BOARD_FILL * cf["height_mm"] / (rows + 1))
        for cf in cfs
    ])  # fmt: skip  # the largest square that fits at each distance
    if room[0] >= square:
        return float(zs[0])
    if room[-1] < square:
        return np.inf
    k = int(np.argmax(room >= square))
    return float(np.interp(square, room[k - 1 : k + 1], zs[k - 1 : k + 1]))


def _boards(optics: TruthOptics, near: float, far: float, margin_px: float, min_px: float):
    """Three boards and the distances each is detectable at.

    The small board fills ``BOARD_FILL`` of the common field at the near end, the large
    one has squares of at least ``MIN_SQUARE_PX`` at the far end and fits from 1/1.6 of
    it, the middle one is their geometric mean. Each board's range runs from where it
    first fits to where its squares shrink to ``MIN_SQUARE_PX`` (within the working
    range); the ranges must overlap so that together they span the working range.
    ``min_px`` is ``MIN_SQUARE_PX``, or ``BLUR_SQUARE_SIGMAS`` PSF sigmas where the
    design's blur is wider.
    """
    zs = np.geomspace(near, far, 7)
    cfs = [common_field(optics, float(z), margin_px) for z in zs]
    focal = np.array([cf["px_per_mm"] * z for cf, z in zip(cfs, zs, strict=True)])
    # the small board: as many corners (up to the default's 8 x 6) as fit BOARD_FILL of
    # the common field at the near end with squares RANGE_RATIO x MIN_SQUARE_PX wide
    room_px = BOARD_FILL * np.array([cfs[0]["width_mm"], cfs[0]["height_mm"]]) * focal[0] / near
    fit = np.floor(room_px / (RANGE_RATIO * min_px)).astype(int) - 1
    cols = int(min(_BOARDS[0][1], fit[0]))
    rows = int(min(_BOARDS[0][2], fit[1], cols - 1))
    if rows < 3:
        raise DesignError(f"the common field at {near:.1f} mm holds no board of 4 x 3 corners")
    layouts = [(_BOARDS[0][0], cols, rows)] + [
        (name, min(c, cols), min(r, rows)) for name, c, r in _BOARDS[1:]
    ]
    small = _round2(
        BOARD_FILL * min(cfs[0]["width_mm"] / (cols + 1), cfs[0]["height_mm"] / (rows + 1)), "down"
    )
    late = common_field(optics, far / 1.6, margin_px)
    _, lcols, lrows = layouts[-1]
    large = max(
        min_px * far / focal[-1],
        BOARD_FILL * min(late["width_mm"] / (lcols + 1), late["height_mm"] / (lrows + 1)),
    )
    large = _round2(large, "up")
    out = []

    def board_range(board, square):
        lo = max(near, _fit_distance(cfs, zs, board, square))
        px = focal * square / zs  # square width in px at each sampled distance
        hi = far if px[-1] >= min_px else float(np.interp(-min_px, -px, zs))
        if not hi >= 1.2 * lo:
            raise DesignError(f"{board[0]} ({square:.3g} mm squares) fits no range of distances")
        return board, square, lo, hi

    out = [board_range(layouts[0], small), None, board_range(layouts[2], large)]
    # the middle board bridges them: it fits by the small one's far end and is still
    # detectable at the large one's near end (the geometric middle of what does both)
    hi_small, lo_large = out[0][3], out[2][2]
    _, mcols, mrows = layouts[1]
    k = int(np.argmin(np.abs(zs - hi_small)))
    fits = BOARD_FILL * min(cfs[k]["width_mm"] / (mcols + 1), cfs[k]["height_mm"] / (mrows + 1))
    seen = min_px * lo_large / float(np.interp(lo_large, zs, focal))
    if not seen <= fits:
        raise DesignError("no middle board bridges the small and the large boards' ranges")
    out[1] = board_range(layouts[1], _round2(np.sqrt(seen * fits)))
    if out[1][2] > out[0][3] or out[2][2] > out[1][3]:
        raise DesignError("the boards' distance ranges leave a gap in the working range")
    return out, cfs, zs, focal


def _targets(boards, scene: dict, charuco_mm: float) -> dict[str, Any]:
    targets = {
        name: {"kind": "chessboard", "cols": cols, "rows": rows, "square_mm": square,
               "margin_squares": 1.0, "black": 0.06, "white": 0.85}
        for (name, cols, rows), square, _, _ in boards
    }  # fmt: skip
    targets["metal"] = scene
    targets["charuco"] = {
        "kind": "charuco", "squares_x": 24, "squares_y": 20, "square_mm": charuco_mm,
        "marker_mm": round(0.75 * charuco_mm, 6), "dictionary": "DICT_4X4_250",
        "texels_per_square": 96, "margin_squares": 1.0, "black": 0.06, "white": 0.85,
    }  # fmt: skip
    return targets


def _focus_and_stop(data: dict, near: float, far: float) -> None:
    """Best focus at the dioptric middle of the working range (equal blur at both ends),
    the f-number raised from its draw until the blur circle there is at most
    ``max_defocus_px`` (up to ``max_f_number``), and the PSF widened by diffraction.

    Notes
    -----
    Blur-circle diameter ``c = A fx |1/z - 1/z_f|`` with ``A = fx pitch / N``, so
    ``N >= fx^2 pitch (1/near - 1/far) / (2 c_max)``; diffraction adds a Gaussian of
    sigma ``0.42 lambda N / pitch`` (the Airy core, lambda = 0.55 um) in quadrature to
    the lens's own ``psf_sigma_px``.
    """
    lens, pitch_mm = data["lens"], data["sensor"]["pixel_pitch_um"] * 1e-3
    lens["best_focus_mm"] = round(2.0 / (1.0 / near + 1.0 / far), 3)
    needed = lens["fx"] ** 2 * pitch_mm * (1.0 / near - 1.0 / far) / (2 * RANGES["max_defocus_px"])
    lens["f_number"] = round(float(min(RANGES["max_f_number"], max(lens["f_number"], needed))), 2)
    diffraction = 0.42 * 0.55e-3 * lens["f_number"] / pitch_mm
    lens["psf_sigma_px"] = round(float(np.hypot(lens["psf_sigma_px"], diffraction)), 3)


def _protocol(rng, optics: TruthOptics, apex_z: float, data: dict) -> dict[str, Any]:
    """Working range, illumination, targets and image sets scaled to the optics.

    ``data`` is the preset so far (sensor, lens, prism); its ``best_focus_mm`` is set here,
    between the ends of the working range, before the apex band's width is known.
    """
    baseline = _baseline(optics)
    near = _convergence(optics, baseline) * _u(rng, RANGES["near_over_convergence"])
    far = near * _u(rng, RANGES["far_over_near"])
    _focus_and_stop(data, near, far)
    # the scenes keep boards APEX_CLEARANCE_SIGMAS band sigmas (and a border) clear of the
    # apex image: the common field the boards are sized for keeps the same clearance
    band = Preset(data).apex_band_sigma_px
    margin = max(4.0, APEX_CLEARANCE_SIGMAS * band + BORDER_CLEARANCE_PX)
    sigma = float(np.max(Preset(data).blur_sigma_px(np.array([near, far]))))
    min_px = max(MIN_SQUARE_PX, BLUR_SQUARE_SIGMAS * sigma)
    boards, cfs, zs, focal = _boards(optics, near, far, margin, min_px)
    width = optics.config.image_size[0]

    def centre_deg(z):
        cf = cfs[int(np.argmin(np.abs(zs - z)))]
        return [round(float(np.degrees(np.arctan(cf[k] / z))), 4) for k in ("x_mm", "y_mm")]

    def offset_deg(z):
        cf = cfs[int(np.argmin(np.abs(zs - z)))]
        return round(float(np.degrees(np.arctan(min(cf["width_mm"], cf["height_mm"]) / z))), 4)

    calib = [
        {"target": name, "images": 12, "distance_mm": [round(lo, 3), round(hi, 3)],
         "centre_deg": centre_deg(lo), "max_offset_deg": offset_deg(lo)}
        for (name, _, _), _, lo, hi in boards
    ]  # fmt: skip
    test = []
    for (name, _, _), square, lo, hi in boards[1:]:
        lo_t, hi_t = lo * 1.03, hi * 0.97
        step = (hi_t - lo_t) / 11.0
        test.append({"target": name, "distance_mm": [round(lo_t, 3), round(lo_t + 11 * step, 3)],
                     "step_mm": round(step, 4), "centre_deg": centre_deg(0.5 * (lo + hi)),
                     "max_offset_mm": round(0.3 * square, 4)})  # fmt: skip
    _, _, lo_m, hi_m = boards[1]
    z_scene = (lo_m, 0.5 * (lo_m + hi_m))
    cf = cfs[int(np.argmin(np.abs(zs - z_scene[0])))]
    mark_scale = 0.5 * min(cf["width_mm"], cf["height_mm"]) / 2.0 / 5.5
    pattern = [[-3.0, -2.5], [2.5, -3.0], [0.5, 0.5], [-2.5, 3.0], [3.0, 2.5], [0.0, -5.5]]
    scene = {
        "kind": "cylinder", "radius_mm": round(z_scene[1] * _u(rng, (0.8, 1.5)), 3),
        "albedo": 0.45, "texture_contrast": 0.35, "specular": 0.35, "shininess": 18.0,
        "texture_seed": int(rng.integers(1, 1000)),
        "mark_radius_mm": round(2.5 * z_scene[1] / float(np.interp(z_scene[1], zs, focal)), 5),
        "mark_albedo": 0.05,
        "marks_mm": [[round(a * mark_scale, 4), round(b * mark_scale, 4)] for a, b in pattern],
    }  # fmt: skip
    charuco_far = 2.0 * near
    charuco_mm = _round2(1.7 * (width / 2.0) / float(focal[0]) * charuco_far / 24.0)
    y_light = 1.7 * baseline
    return {
        "illumination": {
            "sources_mm": [[0.0, -round(y_light, 3), round(apex_z - 0.2, 3)],
                           [0.0, round(y_light, 3), round(apex_z - 0.2, 3)]],
            "lobe_exponent": 1.5, "background_mm": round(2.0 * far, 2), "background_albedo": 0.3,
        },
        "targets": _targets(boards, scene, charuco_mm),
        "sets": {
            "calib": {"boards": calib, "max_tilt_deg": 30.0, "max_roll_deg": 5.0,
                      "partial_images": 2},
            "test": {"boards": test, "max_tilt_deg": 0.5},
            "scene": {"target": "metal", "images": 4,
                      "distance_mm": [round(z_scene[0], 3), round(z_scene[1], 3)],
                      "max_tilt_deg": 15.0, "centre_deg": centre_deg(z_scene[0]),
                      "max_offset_mm": round(0.1 * mark_scale * 5.5, 4)},
            "charuco": {"target": "charuco", "images": 4,
                        "distance_mm": [round(near, 3), round(charuco_far, 3)],
                        "max_tilt_deg": 30.0, "max_roll_deg": 20.0,
                        "max_offset_mm": round(0.2 * near, 3), "min_corners_per_half": 30},
        },
        "_working_range_mm": [near, far],
        "_baseline_mm": baseline,
    }  # fmt: skip


def _render_settings(width: int, height: int) -> dict[str, int]:
    """Supersampling falls with the pixel count so a render's rays stay within a budget
    (the larger sensors' PSF spans more pixels, so fewer samples per pixel suffice)."""
    pixels = width * height
    n = 4 if pixels <= 640 * 512 else 3 if pixels <= 800 * 600 else 2
    return {"supersampling": n, "chunk_rays": 262144}


def _draw_once(seed: int, attempt: int) -> dict[str, Any]:
    """One draw of a whole design; :class:`DesignError` if it is not physical."""
    # the sensor is redrawn only every SENSOR_ATTEMPTS attempts, so the accepted designs
    # keep the sensor formats' weights except where a sensor holds no design at all
    sensor = _sensor(np.random.default_rng([int(seed), 0x73656E73, attempt // SENSOR_ATTEMPTS]))
    rng = np.random.default_rng([int(seed), int(attempt), 0x64657369])
    width, height = sensor["image_size"]
    for _ in range(_LENS_TRIES):  # redraw only the lens while its map folds (cheap)
        try:
            lens = _lens(rng, width, height)
            break
        except DesignError:
            continue
    else:
        raise DesignError("every lens drawn folds inside the image")
    prism = _prism(rng, lens, width, height)
    drawn = {k[1:]: lens.pop(k) for k in [k for k in lens if k.startswith("_")]}
    data: dict[str, Any] = {
        "format": PRESET_FORMAT,
        "version": PRESET_VERSION,
        "name": f"random-{int(seed)}",
        "sensor": sensor,
        "lens": {**lens, "best_focus_mm": 1.0},
        "prism": prism,
    }
    try:
        optics = Preset(data).truth_optics
    except ValueError as exc:  # the apex does not image in the middle row, or worse
        raise DesignError(str(exc)) from None
    check_optics(optics)
    protocol = _protocol(rng, optics, prism["apex_mm"][2], data)
    drawn["working_range_mm"] = [round(v, 3) for v in protocol.pop("_working_range_mm")]
    drawn["baseline_mm"] = round(protocol.pop("_baseline_mm"), 4)
    drawn["wedge_deg"] = [-prism["left_face"]["a_deg"], prism["right_face"]["a_deg"]]
    data.update(protocol)
    data["render"] = _render_settings(width, height)
    data["design"] = {
        "seed": int(seed),
        "attempt": int(attempt),
        "ranges_version": DESIGN_RANGES_VERSION,
        "drawn": drawn,
        "split": optics.config.split,
    }
    data["description"] = (
        f"random design {seed}: {width}x{height} sensor, {drawn['full_field_deg']:.0f} deg lens "
        f"field, {drawn['corner_distortion']:.0%} corner distortion "
        f"({lens['distortion_direction']}), {prism['glass']} biprism, working range "
        f"{drawn['working_range_mm'][0]:.1f}-{drawn['working_range_mm'][1]:.1f} mm "
        "(docs/simulator.md, Design space)"
    )
    return data


def draw_design(seed: int) -> dict[str, Any]:
    """A complete preset document of a plausible biprism probe, a pure function of the seed.

    Parameters
    ----------
    seed : int
        Non-negative design seed.

    Returns
    -------
    dict
        A preset document (``Preset.from_dict`` reads it) with a ``design`` section: the
        seed, the sub-seed attempt that gave a physical design, the ranges' version and
        the drawn values that the preset does not state directly.

    Raises
    ------
    ValueError
        A negative seed, or no physical design within ``MAX_ATTEMPTS`` sub-seeds.
    """
    if int(seed) < 0:
        raise ValueError(f"design seed must be non-negative, not {seed}")
    reasons: list[str] = []
    for attempt in range(MAX_ATTEMPTS):
        try:
            return copy.deepcopy(_draw_once(int(seed), attempt))
        except DesignError as exc:
            reasons.append(str(exc))
    raise ValueError(f"no physical design for seed {seed}; last reasons: {reasons[-3:]}")
