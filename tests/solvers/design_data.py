"""Random probe designs and their calibration corners (a test and bench helper, not a test).

A design is drawn over wide ranges of the forward-view biprism adapters the product
must calibrate (sensor, field, distortion, glass, unequal wedges, tilted rear face,
off-axis apex, prism distance and thickness). Until the simulator's own design space
and truth optics exist, the truth is a :class:`RaytraceModel` with every lens term on;
the calibration never sees the design. Board corners are projected the way the paper
takes calibration images: three boards, twelve poses each over the design's working
range (scaled to where its two views overlap), tilts up to 30 degrees, seeded
Gaussian pixel noise, a few corners lost at the field edge.

Used by ``tests/solvers/test_calibrate_designs.py`` and ``bench/start_designs.py``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from endomeasure.conventions import Half, Status, in_half
from endomeasure.models import ModelConfig, RaytraceModel
from endomeasure.models.raytrace import plane_normal
from endomeasure.solvers.calibrate import ViewDetections

BOARD_COLS, BOARD_ROWS = 7, 5  # inner corners, as the default preset's smallest board
BOARD_RANGES = ((1.0, 1.7), (1.2, 3.0), (2.2, 4.5))
"""Distance ranges of the three boards in units of the near working distance (the
default preset's 10-17, 12-30 and 22-45 mm over a 10 mm near distance)."""
IMAGES_PER_BOARD = 12
EDGE_DROP_PX = 3.0  # corners this close to the split are lost, to the image edge half of them


class Design(NamedTuple):
    truth: RaytraceModel
    summary: str
    near_mm: float


def _split_of(model: RaytraceModel) -> float:
    """Column where the apex images on the central row: where a lens ray, refracted at
    the rear face, meets both front faces at once (the sign change of their distance
    difference), by bisection over the whole width."""
    from endomeasure.geometry.distortion import undistort
    from endomeasure.geometry.rays import intersect_plane, refract

    width, height = model.config.image_size
    (n_rear, d_rear), (n_l, d_l), (n_r, d_r) = (model.face(f) for f in ("rear", "left", "right"))

    def gap(u):
        und = undistort((u - model.cx) / model.fx, np.full_like(u, (height - 1) / 2 - model.cy)
                        / model.fy, model._lens_coeffs(), 1e-12)  # fmt: skip
        d0 = np.stack([und.x, und.y, np.ones_like(u)], -1)
        d0 /= np.linalg.norm(d0, axis=-1, keepdims=True)
        entry = intersect_plane(np.zeros(3), d0, n_rear, d_rear).points
        inside = refract(d0, n_rear, 1.0 / model.n_glass).directions
        return (d_l - entry @ n_l) / (inside @ n_l) - (d_r - entry @ n_r) / (inside @ n_r)

    u = np.linspace(0.0, width - 1.0, 4 * width)
    g = gap(u)
    k = np.flatnonzero((g[:-1] < 0) & (g[1:] > 0))
    if k.size == 0:
        return float("nan")
    a, b = u[k[0]], u[k[0] + 1]
    for _ in range(50):
        m = 0.5 * (a + b)
        a, b = (m, b) if gap(np.array([m]))[0] < 0 else (a, m)
    return float(0.5 * (a + b))


def draw_design(seed: int) -> Design:
    """A random probe as a truth model (redrawn until it images a usable stereo pair)."""
    rng = np.random.default_rng([seed, 7301])
    while True:
        design = _try_design(rng)
        if design is not None:
            return design


def _try_design(rng: np.random.Generator) -> Design | None:
    width = int(round(rng.uniform(320, 1600) / 16) * 16)
    height = int(round(width * rng.choice([0.75, 1.0]) / 8) * 8)
    field = math.radians(rng.uniform(80.0, 140.0))  # full horizontal field of the lens
    barrel = rng.uniform(0.05, 0.35)  # shrink of the edge radius by distortion
    r_edge = math.tan(field / 2) * (1 - barrel)  # distorted normalised radius at u = W/2
    fx = (width / 2) / r_edge
    c = rng.uniform(1.3, 2.0)
    re2 = math.tan(field / 2) ** 2
    k1, k2 = -barrel * c / re2, barrel * (c - 1) / re2**2
    n_glass = rng.uniform(1.45, 1.95)
    wedge_l, wedge_r = np.radians(rng.uniform(15.0, 45.0, 2))
    z_apex = rng.uniform(1.0, 6.0)
    apex = np.array([rng.uniform(-0.12, 0.12) * z_apex, rng.uniform(-0.05, 0.05), z_apex])
    values = dict(
        fx=fx, fy=fx * (1 + rng.uniform(-0.01, 0.01)),
        cx=(width - 1) / 2 + rng.uniform(-0.03, 0.03) * width,
        cy=(height - 1) / 2 + rng.uniform(-0.03, 0.03) * height,
        k1=k1, k2=k2, k3=0.0, p1=0.0, p2=0.0,
        rear_a=math.radians(rng.uniform(-2, 2)), rear_b=math.radians(rng.uniform(-2, 2)),
        rear_d=z_apex * rng.uniform(0.1, 0.6),
        left_a=-wedge_l, left_b=math.radians(rng.uniform(-1, 1)),
        right_a=wedge_r, right_b=math.radians(rng.uniform(-1, 1)),
        n_glass=n_glass,
    )  # fmt: skip
    for face in ("left", "right"):
        values[f"{face}_d"] = float(plane_normal(values[f"{face}_a"], values[f"{face}_b"]) @ apex)
    params = np.array([values.get(k, 0.0) for k in RaytraceModel.PARAM_NAMES])
    try:
        provisional = RaytraceModel(params, ModelConfig((width, height), width // 2))
        u = _split_of(provisional)
    except ValueError:
        return None
    if not (np.isfinite(u) and 0.3 * width < u < 0.7 * width):
        return None
    split = int(math.floor(u + 1.0))
    truth = RaytraceModel(params, ModelConfig((width, height), split))
    near = _near_distance(truth)
    if near is None or near > 15.0 * z_apex:  # views that barely converge: no stereo probe
        return None
    summary = (
        f"{width}x{height} split {split}, field {math.degrees(field):.0f} deg, "
        f"barrel {barrel:.2f}, n {n_glass:.3f}, wedges {math.degrees(wedge_l):.1f}/"
        f"{math.degrees(wedge_r):.1f} deg, apex {apex[0]:+.2f},{apex[2]:.2f} mm, "
        f"rear {values['rear_d']:.2f} mm, near {near:.1f} mm"
    )
    return Design(truth, summary, near)


def _edge_rays(model: RaytraceModel):
    """Per half, the rays of the central row from 5 % to 95 % of the half's width
    (origins, directions); None when one of them is lost in the prism (a real adapter
    has no total internal reflection inside its field)."""
    width, height = model.config.image_size
    split = model.config.split
    out = []
    for half in Half:
        lo, hi = (0, split) if half is Half.LEFT else (split, width)
        u = np.linspace(lo + 0.05 * (hi - lo), hi - 0.05 * (hi - lo), 41)
        rays = model.rays(np.stack([u, np.full_like(u, (height - 1) / 2)], -1), half)
        ok = rays.status == Status.OK
        if not ok.all():
            return None
        out.append((rays.origins[ok], rays.directions[ok]))
    return out


def _field_at(rays, z: float):
    """x extent (lo, hi) and centre of each half's field at depth z, mm."""
    out = []
    for o, d in rays:
        x = o[:, 0] + (z - o[:, 2]) / d[:, 2] * d[:, 0]
        y = o[:, 1] + (z - o[:, 2]) / d[:, 2] * d[:, 1]
        out.append((x.min(), x.max(), np.array([x.mean(), y.mean()])))
    return out


def _near_distance(model: RaytraceModel) -> float | None:
    """Near working distance: the nearest depth at which the two views' fields overlap
    over three quarters of a view's width (the default preset's near distance by this
    rule; a probe is used where both halves see the object); None
    when that never happens within 300 mm."""
    rays = _edge_rays(model)
    if rays is None:
        return None
    for z in np.geomspace(1.0, 300.0, 200):
        (l0, l1, _), (r0, r1, _) = _field_at(rays, z)
        overlap = min(l1, r1) - max(l0, r0)
        if overlap > 0.75 * min(l1 - l0, r1 - r0):
            return float(z)
    return None


def _pose(rng, z: float, centre_xy: np.ndarray, board: np.ndarray, max_tilt_deg: float):
    from tests.solvers.calibration_data import random_tilt

    R = random_tilt(rng, max_tilt_deg)
    centre = np.array([centre_xy[0], centre_xy[1], z])
    return R, centre - R @ board.mean(axis=0)


def _detectable(q: np.ndarray, half: Half, split: int, size, rng) -> np.ndarray:
    """Corners a detector finds: none within ``EDGE_DROP_PX`` of the split (the apex
    band hides them), half of those that close to the outer edges of the image."""
    width, height = size
    lo_u, hi_u = (0, split) if half is Half.LEFT else (split, width)
    at_split = (hi_u - q[:, 0]) if half is Half.LEFT else (q[:, 0] - lo_u)
    outer = (q[:, 0] - lo_u) if half is Half.LEFT else (hi_u - q[:, 0])
    edge = np.minimum.reduce([outer, q[:, 1], height - q[:, 1]])
    lucky = rng.uniform(size=q.shape[0]) < 0.5
    return (at_split > EDGE_DROP_PX) & ((edge > EDGE_DROP_PX) | lucky)


class DesignSet(NamedTuple):
    views: list[ViewDetections]
    boards: dict[str, np.ndarray]
    true_pixels: list[tuple[np.ndarray, np.ndarray]]  # noise-free pixels per view and half
    noise_rms_px: float  # RMS length of detected minus true pixels over all corners


def _noisy_corners(optics, P, noise_px, rng, split, size):
    """Per half: the ids, noisy pixels and exact pixels of the points ``P`` that ``optics``
    projects into the half and a detector would find (:func:`_detectable`)."""
    ids, pixels, exact = [], [], []
    for half in Half:
        proj = optics.project(P, half)
        ok = np.flatnonzero(proj.status == Status.OK)
        q0 = proj.pixels[ok]
        q = q0 + noise_px * rng.standard_normal(q0.shape)
        keep = in_half(q, half, split, size) & _detectable(q, half, split, size, rng)
        ids.append(ok[keep])
        pixels.append(q[keep])
        exact.append(q0[keep])
    return ids, pixels, exact


def design_views(
    design: Design,
    seed: int,
    noise_px: float = 0.04,
    max_tilt_deg: float = 30.0,
    images_per_board: int = IMAGES_PER_BOARD,
) -> DesignSet:
    """Three boards x ``images_per_board`` poses of a design's working range, projected
    by its truth."""
    from tests.solvers.calibration_data import board_corners

    truth = design.truth
    rng = np.random.default_rng([seed, 991])
    width, height = truth.config.image_size
    split = truth.config.split
    rays = _edge_rays(truth)
    views, truths, errors = [], [], []
    boards = {}
    for k, (lo, hi) in enumerate(BOARD_RANGES):
        z_mid = design.near_mm * 0.5 * (lo + hi)
        # a board about half the width one view sees at its mean distance
        (l0, l1, _), (r0, r1, _) = _field_at(rays, z_mid)
        square = 0.5 * min(l1 - l0, r1 - r0) / (BOARD_COLS + 1)
        name = f"board{k}"
        X = board_corners(BOARD_COLS, BOARD_ROWS, square)
        boards[name] = X
        made = 0
        tries = 0
        while made < images_per_board and tries < 40 * images_per_board:
            tries += 1
            z = design.near_mm * (lo + (hi - lo) * (made + rng.uniform()) / images_per_board)
            # halfway between the two fields' centres at this depth, jittered
            (_, _, cl), (_, _, cr) = _field_at(rays, z)
            centre = 0.5 * (cl + cr) + rng.uniform(-0.08, 0.08, 2) * z
            R, t = _pose(rng, z, centre, X, max_tilt_deg)
            P = X @ R.T + t
            ids, pixels, exact = _noisy_corners(truth, P, noise_px, rng, split, (width, height))
            if min(i.size for i in ids) < 12:
                continue
            views.append(ViewDetections(f"{name}_{made:02d}", name, tuple(ids), tuple(pixels)))
            truths.append(tuple(exact))
            errors.extend(p - e for p, e in zip(pixels, exact, strict=True))
            made += 1
    e = np.concatenate(errors)
    return DesignSet(views, boards, truths, float(np.sqrt(np.mean(np.sum(e * e, -1)))))


# ----- the simulator's own design space and truth optics -----------------------------


class TruthSet(NamedTuple):
    """Calibration corners of a drawn design projected by the simulator's truth optics."""

    summary: str
    image_size: tuple[int, int]
    split: int
    n_glass: float
    baseline_mm: float
    sets: DesignSet
    optics: object  # the design's TruthOptics


def truth_design_views(seed: int, noise_px: float = 0.04, images: int | None = None) -> TruthSet:
    """The calibration set of ``simulate.design.draw_design(seed)`` (its boards, its
    protocol of poses), the corners projected by the design's :class:`TruthOptics`
    (optics the calibrated models do not share), with Gaussian noise and a few corners
    lost at the field edge; ``images`` keeps that many, spread over the set."""
    from endomeasure.simulate.design import draw_design
    from endomeasure.simulate.preset import Preset
    from endomeasure.simulate.scenes import plan_set

    data = draw_design(seed)
    preset = Preset.from_dict(data)
    optics = preset.truth_optics
    width, height = optics.config.image_size
    split = optics.config.split
    shots = plan_set(preset, "calib", seed)
    if images is not None:
        keep = np.unique(np.linspace(0, len(shots) - 1, images).round().astype(int))
        shots = [shots[k] for k in keep]
    rng = np.random.default_rng([seed, 4421])
    views, truths, errors, boards = [], [], [], {}
    for shot in shots:
        board = shot.target
        boards.setdefault(board.name, board.corners_board)
        P = board.corners_camera
        ids, pixels, exact = _noisy_corners(optics, P, noise_px, rng, split, (width, height))
        views.append(ViewDetections(shot.name, board.name, tuple(ids), tuple(pixels)))
        truths.append(tuple(exact))
        errors.extend(p - e for p, e in zip(pixels, exact, strict=True))
    e = np.concatenate(errors)
    rms = float(np.sqrt(np.mean(np.sum(e * e, -1))))
    drawn = data["design"]["drawn"]
    prism = data["prism"]
    summary = (
        f"{width}x{height} split {split}, n {optics.n_glass:.3f}, wedges "
        f"{-prism['left_face']['a_deg']:.1f}/{prism['right_face']['a_deg']:.1f} deg, "
        f"field {drawn['full_field_deg']:.0f} deg, distortion {drawn['corner_distortion']:.2f}, "
        f"range {drawn['working_range_mm'][0]:.1f}-{drawn['working_range_mm'][1]:.1f} mm"
    )
    baseline = float(drawn["baseline_mm"])
    return TruthSet(summary, (width, height), split, optics.n_glass, baseline,
                    DesignSet(views, boards, truths, rms), optics)  # fmt: skip
