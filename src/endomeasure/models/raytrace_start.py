"""The ``raytrace`` model's calibration start, from the refined ``pinhole`` pair.

No design data and no nominal prism: the pinhole calibration places every corner in the
left virtual camera's frame, and a search over the prism then finds a start
(:func:`seed_raytrace`):

1. analytic candidates (:func:`_analytic_start`) for each glass index over the
   catalogue range, rear-face depth and distortion start: the lens axis and the
   front-face tilts by a 2-D Snell fit to the virtual cameras' rays (:func:`_plane_fit`),
   the apex on the split column's ray at the depth the virtual centres' spread gives;
2. each fitted by backward traces alone to a few corners per view (:func:`_ray_fit`:
   the corner's pinhole-placed point must lie on its pixel's ray), cheap and without
   ray aiming;
3. the best of each glass refined on the pixels of a few corners of every view with
   the board poses, ranked by that cost (the calibration's own), the winner refined
   once more with the glass free unless calibration holds it.

The calibration's fit over all corners then starts near its optimum. A user's seed
replaces the candidates.
"""

from __future__ import annotations

import math

import numpy as np

from endomeasure.conventions import Half
from endomeasure.errors import CalibrationError
from endomeasure.geometry.rotations import rotation_matrix, rotation_vector
from endomeasure.models.base import ParamBatch
from endomeasure.models.pinhole import PinholeModel
from endomeasure.models.raytrace import DEFAULT_GLASS_INDEX, RaytraceModel, plane_normal
from endomeasure.models.start import Observations, Start, StartContext

__all__ = [
    "seed_raytrace",
    "prism_tilt_for_deviation",
    "GLASS_CANDIDATES",
    "REAR_FRACTIONS",
]


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


GLASS_CANDIDATES = (1.46, 1.62, 1.78, 1.94)
"""Glass indices the start tries when the user gives none: spaced over the optical
glasses of prisms, fused silica (1.458) to dense flints (about 1.95), closely enough
that the fit of the nearest one reaches the basin of the true index."""
REAR_FRACTIONS = (0.3, 0.75)
"""Rear-face depths the start tries, as fractions of the nearest depth where an observed
lens ray meets its front face: a prism most of whose depth is glass, and a thin one
(physically the rear face must lie before every front-face hit; the fits move it)."""
RANK_CORNERS_PER_HALF = 3
"""Corners per image and half of the backward fits (spread over the half's corners): a
few hundred corners over every view rank the candidates as well as all of them."""
RAY_FIT_NFEV = 40  # a cap: a backward fit still far from converged then is a poor candidate
RANKED_PER_GLASS = 2
"""Backward fits of each glass refined on the pixels: the backward cost ranks the
candidates of one glass only roughly."""
FIRST_BUDGET_NFEV = 10
"""Residual evaluations of each ranked candidate in the first round of the halving
(:func:`_halved`); every later round doubles it."""
SAME_COST_FRACTION = 0.01
"""Candidates whose pixel costs differ by less than this fraction reached the same fit."""
PIXEL_CORNERS_PER_HALF = 8
"""Corners per image and half on which the surviving candidates are refined with every
board pose and ranked by pixel cost: every view at a fraction of the full fit's cost,
which then starts near its optimum (continuation from few corners to all)."""


def _plane_fit(pinhole: PinholeModel, obs: Observations, n: float, cx: float, fx: float):
    """Lens axis turn ``psi``, front-face tilts and mean deviations of both halves
    (x-z plane, rad), and the lens ray angles of each half's observed columns.

    The rays of a row of pixels through each half's observed columns, seen by the
    virtual cameras, are matched by the 2-D Snell trace (:func:`_exit_angle`) of the
    same pixels' lens rays, in a frame whose z is the bisector of the virtual axes;
    ``psi`` turns the lens axis about y away from that bisector.
    """
    from scipy.optimize import least_squares

    R_rl, _ = pinhole.pose_right_left()
    bis = np.array([0.0, 0.0, 1.0]) + R_rl.T @ np.array([0.0, 0.0, 1.0])
    R0 = _rotation_between(bis / np.linalg.norm(bis), np.array([0.0, 0.0, 1.0]))
    cy = 0.5 * (pinhole.left_cy + pinhole.right_cy)
    alphas, betas, halves = [], [], []
    for half in Half:
        u_obs = obs.pixels[obs.half == half, 0]
        if u_obs.size < 2:
            continue
        u = np.linspace(*np.percentile(u_obs, [5, 95]), 15)
        d = pinhole.rays(np.stack([u, np.full_like(u, cy)], -1), half).directions @ R0.T
        ok = np.all(np.isfinite(d), axis=-1)
        alphas.append(np.arctan((u[ok] - cx) / fx))
        betas.append(np.arctan2(d[ok, 0], d[ok, 2]))
        halves.append(np.full(int(ok.sum()), int(half)))
    alpha, beta, half = (np.concatenate(a) for a in (alphas, betas, halves))
    mean_dev = [float(np.mean(beta[half == h] - alpha[half == h])) if np.any(half == h)
                else 0.0 for h in (0, 1)]  # fmt: skip

    def residuals(x):
        psi, tilts = x[0], x[1:]
        out = np.array([_exit_angle(a, tilts[h], n) for a, h in zip(alpha, half, strict=True)])
        return np.nan_to_num(out + psi - beta, nan=1.0)

    x0 = np.array([0.0, *(-dev / (n - 1.0) for dev in mean_dev)])
    fit = least_squares(residuals, x0, method="lm", xtol=1e-10)
    psi, tilts = float(fit.x[0]), fit.x[1:]
    devs = [float(np.mean(beta[half == h] - psi - alpha[half == h])) if np.any(half == h)
            else 0.0 for h in (0, 1)]  # fmt: skip
    edges = [alpha[half == h] for h in (0, 1)]
    return R0, psi, tilts, devs, edges


def _analytic_start(
    pinhole: PinholeModel,
    obs: Observations,
    n: float,
    cx: float,
    rear_fraction: float,
    distortion: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``raytrace`` parameters and ``T_raytrace_left`` (R, t) of one candidate.

    Notes
    -----
    ``fx = fy`` (square pixels; a prism magnifies only across its wedge, so ``fy`` is
    the virtual cameras'); the radial distortion none or the virtual cameras' mean (the
    lens's dominates theirs, but a wide prism field bends it); the lens axis and the
    front-face tilts from the 2-D fit :func:`_plane_fit`, the rear face perpendicular to
    the axis; the lens centre midway between the virtual centres; the apex ``z`` from
    the virtual centres' spread (a prism at ``z`` shifts a virtual centre by about
    ``z tan(delta)``) and on the ray of the split column, so that it images there; the
    rear face at ``rear_fraction`` of the nearest depth where an observed lens ray meets
    its front face (the glass must lie between the faces over the whole field).
    """
    names = RaytraceModel.PARAM_NAMES
    split = pinhole.config.split
    fy = 0.5 * (pinhole.left_fy + pinhole.right_fy)
    fx = fy
    cy = 0.5 * (pinhole.left_cy + pinhole.right_cy)
    R0, psi, tilts, devs, edges = _plane_fit(pinhole, obs, n, cx, fx)
    R_rt_left = rotation_matrix(np.array([0.0, -psi, 0.0])) @ R0
    R_rl, t_rl = pinhole.pose_right_left()
    centre_r = -R_rl.T @ t_rl
    lens_centre_left = 0.5 * centre_r
    t_rt_left = -R_rt_left @ lens_centre_left
    alpha_s = math.atan((split - 0.5 - cx) / fx)
    spread = abs(math.tan(devs[0]) - math.tan(devs[1]))
    baseline = float(np.linalg.norm(centre_r))
    z = baseline / spread if spread > 1e-6 and math.isfinite(spread) else 10.0 * baseline
    apex = np.array([z * math.tan(alpha_s), 0.0, z])
    faces = {side: plane_normal(t, 0.0) for side, t in zip(("left", "right"), tilts, strict=True)}
    # depth where each observed lens ray (tan a, 0, 1) meets its half's front face
    hits = [(faces[side] @ apex) / (faces[side] @ np.stack([np.tan(a), 0 * a, 1 + 0 * a]))
            for side, a in zip(("left", "right"), edges, strict=True) if a.size]  # fmt: skip
    z_glass = float(np.min(np.concatenate(hits)))
    if not (z_glass > 0 and math.isfinite(z_glass)):
        raise ValueError("the front faces do not lie in front of the lens")
    values = dict(
        fx=fx, fy=fy, cx=cx, cy=cy, k3=0.0, p1=0.0, p2=0.0,
        k1=0.5 * (pinhole.left_k1 + pinhole.right_k1) if distortion else 0.0,
        k2=0.5 * (pinhole.left_k2 + pinhole.right_k2) if distortion else 0.0,
        rear_a=0.0, rear_b=0.0, rear_d=rear_fraction * z_glass,
        left_a=tilts[0], left_b=0.0, left_d=float(faces["left"] @ apex),
        right_a=tilts[1], right_b=0.0, right_d=float(faces["right"] @ apex),
        n_glass=n,
    )  # fmt: skip
    # lens terms a model adds (extensions) start at zero, their nominal value
    return np.array([values.get(k, 0.0) for k in names]), R_rt_left, t_rt_left


def _ray_fit(model: RaytraceModel, R: np.ndarray, t: np.ndarray, obs: Observations,
             points: np.ndarray, max_nfev: int):  # fmt: skip
    """Fit the free parameters and ``T_raytrace_left`` so that each corner's pixel sees
    its pinhole-placed point ``points`` (M, 3, left frame): backward traces only.

    The residual is the point's offset from the pixel's traced ray, as an angle times
    ``fx`` (about pixels), three components per corner. The Jacobian traces all the
    parameter steps in one batched call (``rays`` with a parameter vector per pixel);
    the pose enters only through the points. Returns (model, R, t, rms px).
    """
    from scipy.optimize import least_squares

    free = np.flatnonzero(model.free_mask)
    F = free.size
    halves = [(half, np.flatnonzero(obs.half == half)) for half in Half]
    base = model.params.copy()
    M = obs.image.size

    def unpack(x):
        p = base.copy()
        p[free] = x[:F]
        return p, x[F : F + 3], x[F + 3 :]

    def trace(table):
        """Origins and directions (K, M, 3) of every corner's pixel under K vectors."""
        K = table.shape[0]
        tracer = model.with_params(table[0])  # a one-row batch traces the model's own faces
        o = np.full((K, M, 3), np.nan)
        d = np.full((K, M, 3), np.nan)
        for half, idx in halves:
            if idx.size == 0:
                continue
            batch = ParamBatch(table, np.repeat(np.arange(K), idx.size))
            rays = tracer.rays(np.tile(obs.pixels[idx], (K, 1)), half, batch)
            o[:, idx] = rays.origins.reshape(K, idx.size, 3)
            d[:, idx] = rays.directions.reshape(K, idx.size, 3)
        return o, d

    def offsets(o, d, rv, tv, fx):
        P = points @ rotation_matrix(rv).T + tv
        e = P - o
        along = np.einsum("...j,...j->...", e, d)
        r = (e - along[..., None] * d) / along[..., None] * np.asarray(fx)[..., None, None]
        bad = ~(np.all(np.isfinite(r), axis=-1) & (along > 0))
        return np.where(bad[..., None], _FAILED_RAY_PX, r)

    def residuals(x):
        p, rv, tv = unpack(x)
        if not model.valid_params(p):
            return np.full(3 * M, _FAILED_RAY_PX)
        o, d = trace(p[None])
        return offsets(o[0], d[0], rv, tv, p[0]).reshape(-1)

    def jacobian(x):
        p, rv, tv = unpack(x)
        steps = _FD_STEP * np.maximum(np.abs(p[free]), 1.0)
        table = np.repeat(p[None], F + 1, axis=0)
        table[np.arange(1, F + 1), free] += steps
        o, d = trace(table)
        r = offsets(o, d, rv, tv, table[:, 0])
        J = np.empty((3 * M, x.size))
        lost = r[1:] == _FAILED_RAY_PX  # a corner lost by a step: no derivative there
        J[:, :F] = np.where(lost, 0.0, (r[1:] - r[0]) / steps[:, None, None]).reshape(F, -1).T
        for k in range(6):
            h = np.zeros(6)
            h[k] = _FD_STEP
            J[:, F + k] = ((offsets(o[0], d[0], rv + h[:3], tv + h[3:], p[0]) - r[0])
                           / _FD_STEP).reshape(-1)  # fmt: skip
        J[~np.isfinite(J)] = 0.0
        failed = np.repeat(np.any(r[0] == _FAILED_RAY_PX, axis=-1), 3)
        J[failed] = 0.0
        return J

    lower = np.full(F + 6, -np.inf)
    for k, i in enumerate(free):
        lower[k] = _LOWER.get(model.PARAM_NAMES[i], -np.inf)
    x0 = np.concatenate([np.maximum(base[free], lower[:F] + 1e-9), rotation_vector(R), t])
    fit = least_squares(residuals, x0, jac=jacobian, method="trf", x_scale="jac",
                        max_nfev=max_nfev, bounds=(lower, np.inf))  # fmt: skip
    p, rv, tv = unpack(fit.x)
    if not model.valid_params(p):
        return model, R, t, math.inf
    rms = float(np.sqrt(np.mean(np.sum(fit.fun.reshape(-1, 3) ** 2, axis=-1))))
    return model.with_params(p), rotation_matrix(rv), tv, rms


_FD_STEP = 1e-6  # relative step of the ray fit's forward differences


_LOWER = {"fx": 1.0, "fy": 1.0, "rear_d": 1e-3, "left_d": 1e-3, "right_d": 1e-3, "n_glass": 1.01}
_FAILED_RAY_PX = 1e3 / math.sqrt(3.0)  # per component: a failed corner costs 1e3 px


def _rank_rows(obs: Observations, per_half: int) -> np.ndarray:
    """A few corners of every image and half, spread over each subset's order."""
    rows = []
    for i in range(obs.n_images):
        for h in (0, 1):
            sel = obs.subset(i, h)
            if sel.size:
                rows.append(sel[np.unique(np.linspace(0, sel.size - 1, per_half).round()
                                          .astype(int))])  # fmt: skip
    return np.sort(np.concatenate(rows))


def _subset(obs: Observations, rows: np.ndarray) -> Observations:
    import dataclasses

    return dataclasses.replace(obs, image=obs.image[rows], half=obs.half[rows],
                               ids=obs.ids[rows], board_points=obs.board_points[rows],
                               pixels=obs.pixels[rows])  # fmt: skip


def _glasses(ctx: StartContext) -> tuple[float, ...]:
    """The glass indices to try: the user's, or the fixed default when calibration holds
    the glass fixed, else every candidate (the data determine it; docs/models.md)."""
    if "n_glass" in ctx.values:
        return (float(ctx.values["n_glass"]),)
    if "n_glass" in ctx.config.fixed:
        return (DEFAULT_GLASS_INDEX,)
    return GLASS_CANDIDATES


def _candidates(ctx: StartContext, pinhole: PinholeModel):
    """The analytic starts to try: every glass of :func:`_glasses`, rear-face depth and
    distortion start, the lens axis on the split column (the apex on the axis: the
    backward fit moves it, and a start on the sensor centre reaches the same fits)."""
    for n in _glasses(ctx):
        for fraction in REAR_FRACTIONS:
            for distortion in (False, True):
                try:
                    yield _analytic_start(pinhole, ctx.obs, n, ctx.config.split - 0.5,
                                          fraction, distortion)  # fmt: skip
                except (ValueError, np.linalg.LinAlgError):
                    continue


def _searched(ctx: StartContext, pinhole: PinholeModel, rvecs, tvecs):
    """The candidate start of least pixel cost (a ``Fit`` with a pose per image).

    Every candidate is fitted by backward traces to a few corners of every view
    (:func:`_ray_fit`, glass held). That cost cannot tell the glasses apart (the pinhole
    pair's own model error limits it), so the best few of each glass are refined on the
    pixels of a few corners of every view with its board poses (from
    ``T_raytrace_left T_left_board``) and its glass still held, and ranked by that
    cost, the calibration's own, by successive halving (:func:`_halved`); the winner is
    refined once more with the glass free unless calibration holds it.
    """
    obs = ctx.obs
    R = rotation_matrix(rvecs)[obs.image]
    P_left = np.einsum("nij,nj->ni", R, obs.board_points) + tvecs[obs.image]
    held = ctx.config.with_fixed(set(ctx.config.fixed) | {"n_glass"})
    rows = _rank_rows(obs, RANK_CORNERS_PER_HALF)
    sub, P_sub = _subset(obs, rows), P_left[rows]
    of_glass = {}
    for params, R_t, t_t in _candidates(ctx, pinhole):
        try:
            model = RaytraceModel(params, held)
        except ValueError:
            continue
        fit = _ray_fit(model, R_t, t_t, sub, P_sub, RAY_FIT_NFEV)
        if math.isfinite(fit[3]):
            of_glass.setdefault(float(params[model.index("n_glass")]), []).append(fit)
    ranked = []
    for fits in of_glass.values():
        ranked.extend(_distinct(fits, lambda f: f[3])[:RANKED_PER_GLASS])
    _debug(f"ray fits: {[(round(f[0].n_glass, 2), round(f[3], 2)) for f in ranked]}")
    views = _subset(obs, _rank_rows(obs, PIXEL_CORNERS_PER_HALF))
    cost, fit = _halved(ctx, views, ranked, rvecs, tvecs)
    if "n_glass" in ctx.config.fixed:
        return fit
    try:
        freed = ctx.refine(fit.model.with_config(fixed=ctx.config.fixed), views, fit.rvecs,
                           fit.tvecs)  # fmt: skip
    except CalibrationError:
        return fit
    freed_cost = _pixel_cost(freed, views)
    _debug(f"glass freed: n {freed.model.n_glass:.3f} cost {freed_cost:.3f}")
    return freed if freed_cost <= cost else fit


def _distinct(items, cost) -> list:
    """``items`` in order of ``cost(item)``, those that reached the same cost as a cheaper
    one (within :data:`SAME_COST_FRACTION`, i.e. the same fit) left out."""
    out = []
    for item in sorted(items, key=cost):
        if not any(abs(cost(item) - cost(d)) <= SAME_COST_FRACTION * cost(d) for d in out):
            out.append(item)
    return out


def _halved(ctx: StartContext, views: Observations, ranked, rvecs, tvecs):
    """The ranked candidates refined on ``views`` by successive halving: every one gets
    :data:`FIRST_BUDGET_NFEV` evaluations, the better half (by pixel cost; candidates
    that reached the same cost count once) twice as many more from where it stopped, and
    so on until one is left, which is refined to convergence. Returns (cost, fit).

    A wrong candidate's cost stays far above the right one's after a few steps, while
    candidates that reach the same fit are refined only once; all of them refined to
    convergence cost several times more.
    """
    alive = []
    for model, R_t, t_t, _ in ranked:
        rv = rotation_vector(R_t @ rotation_matrix(rvecs))
        alive.append((model, rv, tvecs @ R_t.T + t_t, None))
    budget = FIRST_BUDGET_NFEV
    while True:
        last = len(alive) == 1
        scored = []
        for model, rv, tv, state in alive:
            try:
                fit = ctx.refine(model, views, rv, tv, state, None if last else budget)
            except CalibrationError:
                continue
            scored.append((_pixel_cost(fit, views), fit))
        if not scored:
            raise CalibrationError("no start of the raytrace model traces the corners")
        scored.sort(key=lambda cf: cf[0])
        _debug(f"halving, budget {budget}: {[(round(c, 3), f.nfev) for c, f in scored]}")
        if last:
            return scored[0]
        distinct = _distinct(scored, lambda cf: cf[0])
        keep = distinct[: max(1, len(distinct) // 2)]
        alive = [(f.model, f.rvecs, f.tvecs, f.state) for _, f in keep]
        budget *= 2


def _pixel_cost(fit, obs: Observations) -> float:
    """RMS pixel residual of a fit over its observations (a failed corner costs 1e3 px)."""
    projector = fit.model.projector(obs.half)
    R = rotation_matrix(fit.rvecs)[obs.image]
    P = np.einsum("nij,nj->ni", R, obs.board_points) + fit.tvecs[obs.image]
    q, ok = projector.project(fit.model, P)
    r = np.where(ok[:, None], q - obs.pixels, _FAILED_RAY_PX)
    return float(np.sqrt(np.mean(np.sum(r * r, axis=-1))))


def seed_raytrace(ctx: StartContext, base: Start) -> Start:
    """A ``raytrace`` model and board poses to start the joint refinement from.

    Parameters
    ----------
    ctx : StartContext
        ``ctx.seed`` (a raytrace model with design values) replaces the search;
        ``ctx.values`` may set ``n_glass`` (then the only glass tried); a glass held
        fixed by ``ctx.config`` and not set is the catalogue default.
    base : Start
        The refined pinhole pair with ``T_left_board`` per image.

    Returns
    -------
    Start
        ``T_raytrace_board`` per image.

    Notes
    -----
    All corners are placed in the left virtual frame by the pinhole calibration. The
    search (:func:`_searched`) picks a candidate (glass, rear-face depth) by the pixel
    cost on a few corners of every view; a user's seed replaces the candidates. Each
    board pose starts at ``T_raytrace_left T_left_board``; the fit on few corners
    brings the start near the calibration's optimum, which the calibration's own fit on
    all corners then reaches in few steps. No design data is needed.
    """
    pinhole, rvecs, tvecs = base.model, base.rvecs, base.tvecs
    if not isinstance(pinhole, PinholeModel):
        raise TypeError("the raytrace start needs a pinhole calibration")
    if ctx.seed is None:
        fit = _searched(ctx, pinhole, rvecs, tvecs)
        origin = "a search from the pinhole pair"
    else:
        fit = _seeded(ctx, pinhole, rvecs, tvecs)
        origin = "the seed model"
    return Start(fit.model.with_config(fixed=ctx.config.fixed), fit.rvecs, fit.tvecs, origin)


def _seeded(ctx: StartContext, pinhole: PinholeModel, rvecs, tvecs):
    """The user's seed fitted to the pinhole-placed corners by backward traces, then on
    the pixels of a few corners of every view (a ``Fit``)."""
    obs = ctx.obs
    R = rotation_matrix(rvecs)[obs.image]
    P_left = np.einsum("nij,nj->ni", R, obs.board_points) + tvecs[obs.image]
    fixed = frozenset(set(ctx.config.fixed) | {"n_glass"})
    try:
        seeded = RaytraceModel(ctx.seed.params, ctx.config.with_fixed(fixed))
        seeded = seeded.with_values(dict(ctx.values))
    except ValueError as exc:
        raise CalibrationError(f"cannot seed the raytrace model: {exc}") from None
    model, R_t, t_t, _ = _ray_fit(seeded, *_seed_frame(seeded, pinhole), obs, P_left,
                                  RAY_FIT_NFEV)  # fmt: skip
    rv = rotation_vector(R_t @ rotation_matrix(rvecs))
    tv = tvecs @ R_t.T + t_t
    views = _subset(obs, _rank_rows(obs, PIXEL_CORNERS_PER_HALF))
    return ctx.refine(model.with_config(fixed=ctx.config.fixed), views, rv, tv)


def _seed_frame(model: RaytraceModel, pinhole: PinholeModel):
    """``T_raytrace_left`` for a user's seed: the lens centre midway between the virtual
    centres, its axis on the bisector of the virtual axes."""
    R_rl, t_rl = pinhole.pose_right_left()
    bis = np.array([0.0, 0.0, 1.0]) + R_rl.T @ np.array([0.0, 0.0, 1.0])
    R0 = _rotation_between(bis / np.linalg.norm(bis), np.array([0.0, 0.0, 1.0]))
    return R0, -R0 @ (0.5 * (-R_rl.T @ t_rl))


def _debug(text):
    import os
    import sys

    if os.environ.get("EM_DEBUG"):
        sys.stderr.write(text + "\n")
