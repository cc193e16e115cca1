"""Starting values for calibration, without prism design data (SPEC 6).

The chain:

1. :func:`initial_pinhole` — each half calibrated on its own with OpenCV
   (``cv2.calibrateCamera``, Zhang's method), giving two virtual cameras and a board
   pose per image and half; the right camera's pose relative to the left is the
   rotation average and the translation median over the images seen in both halves.
2. (the caller refines the ``pinhole`` pair jointly.)
3. :func:`seed_raytrace` — the ``raytrace`` model from the pinhole pair: the lens camera
   internals from the virtual cameras, the prism from the angle between the virtual
   cameras, the lens frame from their geometry; then one rigid transform and the
   prism are fitted to the corners placed by the pinhole calibration, and the board
   poses are transferred.
"""

from __future__ import annotations

import math

import numpy as np

from endomeasure.conventions import Half
from endomeasure.errors import BadInputError, CalibrationError
from endomeasure.geometry.rotations import rotation_matrix, rotation_vector
from endomeasure.models import ModelConfig, PinholeModel, RaytraceModel

__all__ = [
    "initial_pinhole",
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


def _calibrate_half(obs, half: Half, image_size, split):
    import cv2

    width, height = image_size
    offset = 0.0 if half is Half.LEFT else float(split)
    size = (split, height) if half is Half.LEFT else (width - split, height)
    images, objp, imgp = [], [], []
    for i in range(obs.n_images):
        sel = obs.subset(i, int(half))
        if sel.size == 0:
            continue
        images.append(i)
        objp.append(obs.board_points[sel].astype(np.float32).reshape(-1, 1, 3))
        q = obs.pixels[sel] - np.array([offset, 0.0])
        imgp.append(q.astype(np.float32).reshape(-1, 1, 2))
    try:
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
            objp, imgp, size, None, None, flags=cv2.CALIB_FIX_K3
        )
    except cv2.error as exc:
        raise CalibrationError(
            f"the initial calibration of the {half.label} half failed "
            f"({str(exc).strip().splitlines()[-1]})",
            hint="check that the boards are tilted and at several distances",
        ) from None
    dist = np.asarray(dist, dtype=np.float64).reshape(-1)
    k1, k2, p1, p2, k3 = (list(dist[:5]) + [0.0] * 5)[:5]
    intr = np.array([K[0, 0], K[1, 1], K[0, 2] + offset, K[1, 2], k1, k2, p1, p2, k3])
    rv = np.array([np.asarray(r, dtype=np.float64).reshape(3) for r in rvecs])
    tv = np.array([np.asarray(t, dtype=np.float64).reshape(3) for t in tvecs])
    if not (np.all(np.isfinite(intr)) and intr[0] > 0 and intr[1] > 0 and np.isfinite(rms)):
        raise CalibrationError(
            f"the initial calibration of the {half.label} half failed (no valid focal length)",
            hint="check that the boards are tilted and at several distances",
        )
    return intr, dict(zip(images, zip(rv, tv, strict=False), strict=False)), float(rms)


def _mean_rotation(Rs: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of rotation matrices: the rotation nearest to their average."""
    U, _, Vt = np.linalg.svd(Rs.mean(axis=0))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def initial_pinhole(obs, image_size, split) -> tuple[PinholeModel, np.ndarray, np.ndarray]:
    """Per-half OpenCV calibration combined into a ``pinhole`` pair.

    Parameters
    ----------
    obs : Observations
        From :mod:`endomeasure.solvers.calibrate`.
    image_size : (width, height), px
    split : int

    Returns
    -------
    model : PinholeModel
    rvecs, tvecs : ndarray, shape (I, 3)
        ``T_left_board`` per image (rad, mm).
    """
    intr_l, poses_l, _ = _calibrate_half(obs, Half.LEFT, image_size, split)
    intr_r, poses_r, _ = _calibrate_half(obs, Half.RIGHT, image_size, split)
    both = sorted(set(poses_l) & set(poses_r))
    if not both:
        raise CalibrationError("no image shows the board in both halves")
    Rl = rotation_matrix(np.array([poses_l[i][0] for i in both]))
    Rr = rotation_matrix(np.array([poses_r[i][0] for i in both]))
    tl = np.array([poses_l[i][1] for i in both])
    tr = np.array([poses_r[i][1] for i in both])
    R_rl = _mean_rotation(Rr @ np.swapaxes(Rl, -1, -2))
    t_rl = np.median(tr - tl @ R_rl.T, axis=0)
    rvecs = np.zeros((obs.n_images, 3))
    tvecs = np.zeros((obs.n_images, 3))
    for i in range(obs.n_images):
        if i in poses_l:
            rvecs[i], tvecs[i] = poses_l[i]
        else:
            rv, tv = poses_r[i]
            rvecs[i] = rotation_vector(R_rl.T @ rotation_matrix(rv))
            tvecs[i] = R_rl.T @ (tv - t_rl)
    params = np.concatenate([intr_l, intr_r, rotation_vector(R_rl), t_rl])
    return PinholeModel(params, ModelConfig(tuple(image_size), split)), rvecs, tvecs


# ----- pinhole -> raytrace ---------------------------------------------------------------------


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


def seed_raytrace(pinhole, obs, rvecs, tvecs, fixed, options):
    """A ``raytrace`` model and board poses to start the joint refinement from.

    Parameters
    ----------
    pinhole : PinholeModel
        The refined pinhole pair.
    obs : Observations
    rvecs, tvecs : ndarray, shape (I, 3)
        ``T_left_board`` per image from the pinhole calibration.
    fixed : frozenset of str
        Parameters the raytrace calibration holds fixed.
    options : CalibrationOptions

    Returns
    -------
    model : RaytraceModel
    rvecs, tvecs : ndarray, shape (I, 3)
        ``T_raytrace_board`` per image.
    nfev : int
        Residual evaluations spent.
    state : ndarray or None
        Projector warm-start state per observation (lens coordinates).

    Notes
    -----
    After the analytic start (:func:`raytrace_from_pinhole`, or the user's seed values)
    all corners are placed in the left virtual frame by the pinhole calibration, and
    the free prism and lens parameters are fitted together with a single rigid
    transform ``T_raytrace_left`` to their detected pixels: a small problem (F + 6
    unknowns) that moves the start into the basin of the joint fit, after which each
    board pose is ``T_raytrace_left T_left_board``.
    """
    from endomeasure.solvers.calibrate import DEFAULT_GLASS_INDEX, Observations, refine

    names = RaytraceModel.PARAM_NAMES
    params, R_t, t_t = raytrace_from_pinhole(
        pinhole, options.glass_index if options.glass_index is not None else DEFAULT_GLASS_INDEX
    )
    if options.seed is not None:
        seed = dict(options.seed)
        if seed.get("model") != RaytraceModel.NAME:
            raise BadInputError(
                f"the seed describes a {seed.get('model')!r} model, not a raytrace model",
                hint="give a raytrace model file (as written by `endomeasure export`)",
            )
        seed_names = tuple(seed.get("param_names", names))
        if seed_names != names or len(seed.get("params", ())) != len(names):
            raise BadInputError("the seed's raytrace parameters do not match this version")
        params = np.asarray(seed["params"], dtype=np.float64)
        if options.glass_index is not None:
            params[names.index("n_glass")] = options.glass_index
    config = ModelConfig(pinhole.config.image_size, pinhole.config.split, fixed)
    try:
        model = RaytraceModel(params, config)
    except ValueError as exc:
        raise CalibrationError(f"cannot seed the raytrace model: {exc}") from None
    # corners in the left virtual frame, fitted as one rigid "board"
    R = rotation_matrix(rvecs)[obs.image]
    P_left = np.einsum("nij,nj->ni", R, obs.board_points) + tvecs[obs.image]
    one = Observations(
        image_names=("all",),
        image_boards=("all",),
        image=np.zeros(obs.image.size, dtype=np.int64),
        half=obs.half,
        ids=obs.ids,
        board_points=P_left,
        pixels=obs.pixels,
        skipped=(),
    )
    rv0 = rotation_vector(R_t)[None]
    fit = refine(model, one, rv0, t_t[None], np.ones(obs.image.size, bool), options.max_nfev)
    R_t = rotation_matrix(fit.rvecs[0])
    t_t = fit.tvecs[0]
    R_b = rotation_matrix(rvecs)
    new_r = rotation_vector(R_t @ R_b)
    new_t = tvecs @ R_t.T + t_t
    return fit.model, new_r, new_t, fit.nfev, fit.state
