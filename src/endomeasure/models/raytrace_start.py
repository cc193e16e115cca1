"""The ``raytrace`` model's calibration start, from the refined ``pinhole`` pair.

The lens camera internals come from the virtual cameras, the prism from the angle
between them, the lens frame from their geometry (:func:`raytrace_from_pinhole`), or
all of it from the user's seed; then one rigid transform and the free parameters are
fitted to the corners placed by the pinhole calibration, and the board poses are
transferred (:func:`seed_raytrace`). No prism design data is needed.
"""

from __future__ import annotations

import math

import numpy as np

from endomeasure.errors import CalibrationError
from endomeasure.geometry.rotations import rotation_matrix, rotation_vector
from endomeasure.models.pinhole import PinholeModel
from endomeasure.models.raytrace import DEFAULT_GLASS_INDEX, RaytraceModel
from endomeasure.models.start import Start, StartContext

__all__ = [
    "raytrace_from_pinhole",
    "seed_raytrace",
    "prism_tilt_for_deviation",
    "NOMINAL_PRISM_THICKNESS_RATIO",
]

NOMINAL_PRISM_THICKNESS_RATIO = 0.75
"""Seed prism thickness (rear face to apex) as a fraction of the effective prism
distance. Only a start value: the joint fit moves the faces; the value matters little
because thickness and distance enter the projections almost only through the
baseline they produce."""
_MIN_PRISM_DISTANCE_MM = 0.3
_MAX_PRISM_DISTANCE_MM = 20.0


def _exit_angle(alpha: float, tilt: float, n: float) -> float:
    """2-D trace in the x-z plane: a ray at ``alpha`` from the axis through a prism whose
    rear face is perpendicular to the axis and whose front face normal is tilted by
    ``tilt`` (both angles positive toward +x); returns the exit angle (rad)."""
    inside = math.asin(math.sin(alpha) / n)
    s = n * math.sin(inside - tilt)
    if abs(s) >= 1.0:
        return math.nan  # total internal reflection
    return tilt + math.asin(s)


def prism_tilt_for_deviation(alpha: float, beta: float, n: float) -> float:
    """Front-face tilt that turns a ray at angle ``alpha`` into one at ``beta``.

    Parameters
    ----------
    alpha, beta : float, rad
        Ray angles from the lens axis in the x-z plane before and after the prism.
    n : float
        Glass index.

    Returns
    -------
    float, rad
        The tilt ``a`` of the front face (the ``raytrace`` parameter ``*_a``).

    Notes
    -----
    The thin-prism rule ``delta ~ (n - 1) A`` (deviation ``delta = beta - alpha`` for a
    prism of apex angle ``A = -a``) gives the start; Newton's method on the exact 2-D
    Snell trace :func:`_exit_angle` then corrects it for the oblique incidence.
    """
    a = -(beta - alpha) / (n - 1.0)
    for _ in range(30):
        g = _exit_angle(alpha, a, n) - beta
        h = 1e-7
        dg = (_exit_angle(alpha, a + h, n) - _exit_angle(alpha, a - h, n)) / (2 * h)
        if not (math.isfinite(g) and math.isfinite(dg)) or dg == 0.0:
            return -(beta - alpha) / (n - 1.0)  # keep the thin-prism value
        step = g / dg
        a -= step
        if abs(step) < 1e-12:
            break
    return a


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector a to unit vector b."""
    axis = np.cross(a, b)
    s = np.linalg.norm(axis)
    if s < 1e-15:
        return np.eye(3)
    angle = math.atan2(s, float(a @ b))
    return rotation_matrix(axis / s * angle)


def raytrace_from_pinhole(
    pinhole: PinholeModel, n_glass: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Analytic ``raytrace`` parameters and the lens frame from a ``pinhole`` pair.

    Parameters
    ----------
    pinhole : PinholeModel
    n_glass : float

    Returns
    -------
    params : ndarray, shape (19,)
        ``raytrace`` parameters in ``RaytraceModel.PARAM_NAMES`` order.
    R_rt_left, t_rt_left : ndarray, shapes (3, 3), (3,)
        ``T_raytrace_left``: maps the pinhole (left virtual camera) frame into the lens
        frame.

    Notes
    -----
    Assumes a biprism symmetric about the lens axis:

    - the lens axis bisects the two virtual optical axes, and the lens centre is the
      midpoint of the two virtual centres;
    - ``fx, fy`` are the mean virtual focal lengths, ``cy`` the mean virtual ``cy``,
      ``cx`` the split (the apex edge lies on the axis), no distortion;
    - the pixel ``cx`` of a virtual camera sees, through the lens, the direction
      ``alpha = atan((cx_v - cx) / fx)``; through the prism it must leave along the
      virtual axis, at ``beta = -+ phi / 2`` (``phi`` the angle between the virtual axes),
      so the front face tilt follows from the deviation ``beta - alpha``
      (:func:`prism_tilt_for_deviation`), the rear face perpendicular to the axis;
    - a thin prism at distance ``z`` shifts a virtual centre sideways by about
      ``z tan(delta)``, so ``z ~ baseline / |tan delta_L - tan delta_R|`` places the
      prism; the rear face and the apex sit at ``z -+ thickness / 2``.
    """
    names = RaytraceModel.PARAM_NAMES
    split = pinhole.config.split
    R_rl, t_rl = pinhole.pose_right_left()
    axis_l = np.array([0.0, 0.0, 1.0])
    axis_r = R_rl.T @ axis_l  # right virtual axis in the left frame
    centre_r = -R_rl.T @ t_rl
    bisector = axis_l + axis_r
    bisector /= np.linalg.norm(bisector)
    R_left_rt = _rotation_between(np.array([0.0, 0.0, 1.0]), bisector)
    R_rt_left = R_left_rt.T
    lens_centre_left = 0.5 * centre_r  # midpoint of the virtual centres, left frame
    t_rt_left = -R_rt_left @ lens_centre_left
    # virtual axes in the lens frame, as angles in the x-z plane
    a_l, a_r = R_rt_left @ axis_l, R_rt_left @ axis_r
    beta_l = math.atan2(a_l[0], a_l[2])
    beta_r = math.atan2(a_r[0], a_r[2])
    fx = 0.5 * (pinhole.left_fx + pinhole.right_fx)
    fy = 0.5 * (pinhole.left_fy + pinhole.right_fy)
    cx = split - 0.5
    cy = 0.5 * (pinhole.left_cy + pinhole.right_cy)
    alpha_l = math.atan((pinhole.left_cx - cx) / fx)
    alpha_r = math.atan((pinhole.right_cx - cx) / fx)
    tilt_l = prism_tilt_for_deviation(alpha_l, beta_l, n_glass)
    tilt_r = prism_tilt_for_deviation(alpha_r, beta_r, n_glass)
    spread = abs(math.tan(beta_l - alpha_l) - math.tan(beta_r - alpha_r))
    baseline = float(np.linalg.norm(centre_r))
    z = baseline / spread if spread > 1e-6 else 2.0
    z = min(max(z, _MIN_PRISM_DISTANCE_MM), _MAX_PRISM_DISTANCE_MM)
    half_thick = 0.5 * NOMINAL_PRISM_THICKNESS_RATIO * z
    rear, apex = z - half_thick, z + half_thick
    values = dict(
        fx=fx, fy=fy, cx=cx, cy=cy, k1=0.0, k2=0.0, k3=0.0, p1=0.0, p2=0.0,
        rear_a=0.0, rear_b=0.0, rear_d=rear,
        left_a=tilt_l, left_b=0.0, left_d=apex * math.cos(tilt_l),
        right_a=tilt_r, right_b=0.0, right_d=apex * math.cos(tilt_r),
        n_glass=n_glass,
    )  # fmt: skip
    return np.array([values[k] for k in names]), R_rt_left, t_rt_left


def seed_raytrace(ctx: StartContext, base: Start) -> Start:
    """A ``raytrace`` model and board poses to start the joint refinement from.

    Parameters
    ----------
    ctx : StartContext
        ``ctx.seed`` (a raytrace model with design values) replaces the analytic start;
        ``ctx.values`` may set ``n_glass``.
    base : Start
        The refined pinhole pair with ``T_left_board`` per image.

    Returns
    -------
    Start
        ``T_raytrace_board`` per image, and the projector state of the seeding fit.

    Notes
    -----
    After the analytic start (:func:`raytrace_from_pinhole`, or the seed's values) all
    corners are placed in the left virtual frame by the pinhole calibration, and the
    free prism and lens parameters are fitted together with a single rigid transform
    ``T_raytrace_left`` to their detected pixels: a small problem (F + 6 unknowns) that
    moves the start into the basin of the joint fit, after which each board pose is
    ``T_raytrace_left T_left_board``.
    """
    pinhole, rvecs, tvecs = base.model, base.rvecs, base.tvecs
    if not isinstance(pinhole, PinholeModel):
        raise TypeError("the raytrace start needs a pinhole calibration")
    n_glass = ctx.values.get("n_glass", DEFAULT_GLASS_INDEX)
    params, R_t, t_t = raytrace_from_pinhole(pinhole, n_glass)
    if ctx.seed is not None:
        params = ctx.seed.params
    try:
        model = RaytraceModel(params, ctx.config).with_values(dict(ctx.values))
    except ValueError as exc:
        raise CalibrationError(f"cannot seed the raytrace model: {exc}") from None
    obs = ctx.obs
    R = rotation_matrix(rvecs)[obs.image]
    P_left = np.einsum("nij,nj->ni", R, obs.board_points) + tvecs[obs.image]
    fit = ctx.refine(model, obs.as_one_board(P_left), rotation_vector(R_t)[None], t_t[None])
    R_t = rotation_matrix(fit.rvecs[0])
    t_t = fit.tvecs[0]
    new_r = rotation_vector(R_t @ rotation_matrix(rvecs))
    new_t = tvecs @ R_t.T + t_t
    origin = "the seed model" if ctx.seed is not None else "the pinhole pair"
    return Start(fit.model, new_r, new_t, origin, fit.state)
