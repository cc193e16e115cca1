"""Sub-pixel chessboard corners as centres of point symmetry, and a saddle-fit peer.

Near an inner corner a chessboard image is point-symmetric: opposite quadrants have the
same colour, so ``I(c + h) = I(c - h)``. This holds exactly for any perspective view
(the two grid lines through the corner stay straight lines through it, and two lines
through a point are their own 180-degree image) and for any point-symmetric blur, as
long as the window stays inside the four squares around the corner. It does not depend
on image gradients, which is why it is less biased than ``cv2.cornerSubPix`` by blur,
8-bit edges and strong perspective (measured in ``docs/accuracy.md``, "Detection").

:func:`symmetric_corners` minimises, per corner, over the corner ``c`` and a relative
illumination gradient ``k`` (vignetting, light fall-off; without it the fit is pulled
along the brighter diagonal, alternately for the two corner colourings)::

    E(c, k) = sum_h w(h) [I(c + h) - I(c - h) - (k . h) (I(c + h) + I(c - h))]^2

over integer offsets ``h`` (so that every sample of one corner has the same sub-pixel
phase and one separable 4 x 4 interpolation serves the whole window). ``I`` is the
cubic B-spline interpolant of the image; ``w`` is a Gaussian window defined on the
board (through the local affine map of the detected grid, so it follows perspective and
the prism's anamorphic squeeze), of standard deviation :data:`SYMMETRY_SIGMA_SQUARES`
squares, cut at twice that. Gauss-Newton in the four unknowns, vectorised over corners,
converges in 3-5 iterations from the sector-based detector's corners.

Lens and prism distortion curve the grid lines, and the image around a corner is then
not point-symmetric: to second order the grid maps as ``p(d) = c + A d + s(d)`` with
``s(d)`` quadratic, the same for ``d`` and ``-d``. Given the curvature (from
:func:`local_quadratic`, a quadratic fit to the detected neighbours), the compared pair
is ``c + h + s(A^-1 h)`` and ``c - h + s(A^-1 h)``: the images of two board points
symmetric about the corner. The plain comparison is pulled outwards, mirrored in the two
halves, which calibration turns into a scale error; the curvature-aware one has no
measurable bias (``docs/accuracy.md``, "Detection", "Against the simulator").

:func:`saddle_corners` is the classic peer: a quadratic surface fitted to the image in
the same window, its saddle point the corner (kept selectable for the comparison).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from endomeasure.interpolation import bspline_weights, spline_coefficients, spline_sample

__all__ = [
    "SYMMETRY_SIGMA_SQUARES",
    "SubpixelResult",
    "SymmetricProblem",
    "local_quadratic",
    "local_steps",
    "saddle_corners",
    "symmetric_corners",
    "symmetric_problem",
    "symmetric_system",
]

# Gaussian window sigma in squares. Larger windows average more pixels but, without the
# curvature-aware pairs, feel more of the distortion's curvature of the lines, and beyond
# about half a square they reach the next grid lines. Chosen on the default preset's
# renders with SB's own corners as the start; `bench/bench_detect.py refinement` sweeps
# the sigma only for that start and runs the adopted variant (cornerSubPix start,
# curvature-aware pairs) at this value alone, where earlier development runs found
# 0.4-0.5 better on noise-free sets: not re-chosen yet (docs/accuracy.md, "Design
# measurements behind the code's constants").
SYMMETRY_SIGMA_SQUARES = 0.3
# The saddle fit's window sigma in squares (a quadratic surface fits only close to the
# corner): chosen in development runs on the default preset (docs/accuracy.md, "Design
# measurements"); the bench command runs the saddle fit at this value only.
SADDLE_SIGMA_SQUARES = 0.1
# Window cut at this many sigmas: 0.6 squares, inside the four squares around a corner
# with room for the blur of the next grid lines.
SYMMETRY_TRUNCATE = 2.0
# Half side of the pixel box holding the window: large squares use a box this size.
SYMMETRY_MAX_HALFSIZE_PX = 12
# Gauss-Newton: stop when every corner moves less than this; at most this many steps.
SYMMETRY_TOLERANCE_PX = 1e-3
SYMMETRY_MAX_ITERATIONS = 20
# A step is shortened to this length (the start is within a pixel of the corner).
SYMMETRY_MAX_STEP_PX = 0.5
# A corner that ends further than this from its start did not converge (the detectors'
# corners are within 1 px of the truth).
SYMMETRY_MAX_SHIFT_PX = 1.5
# Offsets whose interpolation support (2 px) could leave the image after the largest
# shift are dropped, with their mirror: the window is clipped point-symmetrically.
BORDER_GUARD_PX = 2 + SYMMETRY_MAX_SHIFT_PX
# Fewest pixel pairs a clipped window must keep.
MIN_WINDOW_PAIRS = 8
# Corners either side of a corner (per grid axis) whose detected pixels give its local
# quadratic grid map (the curvature of the grid lines).
CURVATURE_RADIUS = 2


@dataclasses.dataclass(frozen=True)
class SubpixelResult:
    """Refined corners.

    Attributes
    ----------
    pixels : ndarray, shape (n, 2), px
    converged : ndarray, shape (n,), bool
        False where the window left the image, the fit was singular or did not settle;
        the pixel is then the start.
    """

    pixels: np.ndarray
    converged: np.ndarray


def local_steps(grid: np.ndarray) -> np.ndarray:
    """Local affine map of a corner grid: the steps to the next column and row, px.

    Parameters
    ----------
    grid : ndarray, shape (rows, cols, 2), px

    Returns
    -------
    ndarray, shape (rows * cols, 2, 2)
        Columns: the step along the grid's columns, then along its rows (central
        differences inside the grid, one-sided at its border).
    """
    grid = np.asarray(grid, dtype=np.float64)
    rows, cols = grid.shape[:2]
    if rows < 2 or cols < 2:
        raise ValueError(f"a corner grid needs at least 2 x 2 corners, got {rows} x {cols}")
    step_col = np.gradient(grid, axis=1).reshape(-1, 2)
    step_row = np.gradient(grid, axis=0).reshape(-1, 2)
    return np.stack([step_col, step_row], axis=-1)


def local_quadratic(
    grid: np.ndarray, radius: int = CURVATURE_RADIUS
) -> tuple[np.ndarray, np.ndarray]:
    """Local second-order map of a corner grid: steps and curvature of every corner.

    Fits, per corner, ``p(dc, dr) = p0 + a dc + b dr + q_cc dc^2 + q_cr dc dr + q_rr dr^2``
    (``dc``, ``dr`` column and row offsets on the grid from that corner) by least squares
    to the detected pixels of the ``(2 radius + 1)^2`` corners around it; a corner too near
    the grid's border uses the nearest full neighbourhood (the expansion is still about the
    corner itself).

    Parameters
    ----------
    grid : ndarray, shape (rows, cols, 2), px
    radius : int
        Neighbourhood half size in corners.

    Returns
    -------
    steps : ndarray, shape (rows * cols, 2, 2), px
        Columns ``a`` and ``b`` (as :func:`local_steps`).
    curvature : ndarray, shape (rows * cols, 2, 3), px
        Columns ``q_cc``, ``q_cr``, ``q_rr``: the second-order displacement of the
        grid point at step offset ``d`` is ``q_cc d0^2 + q_cr d0 d1 + q_rr d1^2``. A grid
        with fewer than 3 rows (columns) gets no curvature along its rows (columns).
    """
    grid = np.asarray(grid, dtype=np.float64)
    rows, cols = grid.shape[:2]
    if rows < 2 or cols < 2:
        raise ValueError(f"a corner grid needs at least 2 x 2 corners, got {rows} x {cols}")

    def axis(count: int) -> tuple[np.ndarray, int]:
        span = min(2 * radius + 1, count)
        first = np.clip(np.arange(count) - span // 2, 0, count - span)
        return first[:, None] + np.arange(span)[None], span  # (count, span) indices

    row_idx, n_r = axis(rows)
    col_idx, n_c = axis(cols)
    # (rows, cols, n_r, n_c) neighbourhood offsets and pixels
    dr = (row_idx - np.arange(rows)[:, None])[:, None, :, None] * np.ones((1, cols, 1, n_c))
    dc = (col_idx - np.arange(cols)[:, None])[None, :, None, :] * np.ones((rows, 1, n_r, 1))
    points = grid[row_idx[:, None, :, None], col_idx[None, :, None, :]]
    design = np.stack([np.ones_like(dc), dc, dr, dc * dc, dc * dr, dr * dr], axis=-1)
    design = design.reshape(rows * cols, n_r * n_c, 6)
    points = points.reshape(rows * cols, n_r * n_c, 2)
    usable = np.array([True, True, True, n_c >= 3, True, n_r >= 3])
    normal = np.matmul(design.transpose(0, 2, 1), design)
    normal[:, ~usable, :] = 0.0
    normal[:, :, ~usable] = 0.0
    normal[:, ~usable, ~usable] = 1.0
    rhs = np.matmul(design.transpose(0, 2, 1), points)
    rhs[:, ~usable] = 0.0
    coef = np.linalg.solve(normal, rhs)  # (n, 6, 2)
    steps = coef[:, 1:3].transpose(0, 2, 1)
    curvature = coef[:, 3:6].transpose(0, 2, 1)
    return steps, curvature


@dataclasses.dataclass(frozen=True)
class _Window:
    """Offsets and per-corner weights of the compared half-window."""

    halfsize: int  # the box is (2 * halfsize + 1) px square
    keep: np.ndarray  # (M,) flat indices into the box of one of each pair (h, -h)
    offsets: np.ndarray  # (M, 2) h, px
    weights: np.ndarray  # (n, M)


def _window(steps: np.ndarray, sigma_squares: float) -> _Window:
    radius = SYMMETRY_TRUNCATE * sigma_squares
    reach = radius * np.abs(steps).sum(axis=-1)  # (n, 2): box half-size per axis
    halfsize = int(min(SYMMETRY_MAX_HALFSIZE_PX, np.ceil(reach.max()) + 1))
    span = np.arange(-halfsize, halfsize + 1)
    hx, hy = np.meshgrid(span, span)
    upper = ((hy > 0) | ((hy == 0) & (hx > 0))).ravel()
    offsets = np.stack([hx.ravel(), hy.ravel()], axis=-1).astype(np.float64)
    # squared length in squares of an offset h: h^T (A^-T A^-1) h, A the local steps
    inverse = np.linalg.inv(steps)
    form = np.matmul(inverse.transpose(0, 2, 1), inverse)
    hu, hv = offsets[:, 0], offsets[:, 1]
    squares2 = (
        form[:, 0, 0, None] * hu * hu
        + 2 * form[:, 0, 1, None] * hu * hv
        + form[:, 1, 1, None] * hv * hv
    )
    distance2 = squares2 / sigma_squares**2
    weights = np.where(distance2 <= SYMMETRY_TRUNCATE**2, np.exp(-0.5 * distance2), 0.0)
    keep = np.flatnonzero(upper & (weights > 0).any(axis=0))
    return _Window(halfsize, keep, offsets[keep], weights[:, keep])


@dataclasses.dataclass(frozen=True)
class SymmetricProblem:
    """The fixed parts of the point-symmetry fit of a set of corners.

    Attributes
    ----------
    window : _Window
        Integer offsets ``h`` (one of each pair ``h``, ``-h``) and their Gaussian weights.
    shift : ndarray, shape (n, M, 2), px, or None
        Second-order displacement ``s`` of each compared pair (curvature-aware pairs
        ``c + s +- h``); None for plain 180-degree pairs.
    coeffs : ndarray, shape (h, w), float32
        Cubic B-spline coefficients of the image box around the corners.
    origin : ndarray, shape (2,), int
        (u, v) of the box's first sample, px.
    weights : ndarray, shape (n, M)
        Window weights with the pairs that would leave the image near its border removed.
    """

    window: _Window
    shift: np.ndarray | None
    coeffs: np.ndarray
    origin: np.ndarray
    weights: np.ndarray


def symmetric_problem(
    gray: np.ndarray,
    start: np.ndarray,
    steps: np.ndarray,
    curvature: np.ndarray | None = None,
    sigma_squares: float = SYMMETRY_SIGMA_SQUARES,
) -> SymmetricProblem:
    """Window, pair displacements, interpolant and border-clipped weights of the fit.

    Parameters
    ----------
    gray : ndarray, shape (height, width)
    start : ndarray, shape (n, 2), px
        Points the interpolant's box and the border clipping are set around.
    steps : ndarray, shape (n, 2, 2), px
        Local affine map of each corner (:func:`local_steps`).
    curvature : ndarray, shape (n, 2, 3), px, optional
        Local curvature (:func:`local_quadratic`); None for plain pairs.
    sigma_squares : float
        Window sigma in squares.

    Returns
    -------
    SymmetricProblem
    """
    c = np.asarray(start, dtype=np.float64)
    n = len(c)
    window = _window(steps, sigma_squares)
    shift = None
    if curvature is not None:
        curvature = np.asarray(curvature, dtype=np.float64)
        if curvature.shape != (n, 2, 3):
            raise ValueError(f"curvature must have shape ({n}, 2, 3), not {curvature.shape}")
        board = np.einsum("nij,mj->nmi", np.linalg.inv(steps), window.offsets)  # d = A^-1 h
        quad = np.stack(
            [board[..., 0] ** 2, board[..., 0] * board[..., 1], board[..., 1] ** 2], axis=-1
        )
        shift = np.einsum("nij,nmj->nmi", curvature, quad)  # (n, M, 2) px
    coeffs, origin = spline_coefficients(gray, c, window.halfsize)
    box_h, box_w = coeffs.shape
    hx, hy = window.offsets[:, 0], window.offsets[:, 1]
    # Near the image border keep only the offsets whose pair stays inside.
    local = c - origin
    room = np.minimum(local, np.array([box_w - 1, box_h - 1]) - local) - BORDER_GUARD_PX
    reach_u, reach_v = np.abs(hx)[None], np.abs(hy)[None]
    if shift is not None:
        reach_u, reach_v = reach_u + np.abs(shift[..., 0]), reach_v + np.abs(shift[..., 1])
    fits = (reach_u <= room[:, 0, None]) & (reach_v <= room[:, 1, None])
    weights = np.where(fits, window.weights, 0.0)
    return SymmetricProblem(window, shift, coeffs, origin, weights)


def symmetric_system(
    problem: SymmetricProblem, c: np.ndarray, k: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Residuals of the symmetric comparison and their Jacobian at ``c`` (and ``k``).

    Parameters
    ----------
    problem : SymmetricProblem
    c : ndarray, shape (n, 2), px
        Corner estimates.
    k : ndarray, shape (n, 2), 1/px, or None
        Relative illumination gradients; None fits none (two unknowns per corner).

    Returns
    -------
    residual : ndarray, shape (n, M)
        ``I(c+s+h) - I(c+s-h) - (k.h) (I(c+s+h) + I(c+s-h))``.
    jacobian : ndarray, shape (n, M, p)
        d residual / d (u, v[, k_u, k_v]); ``p`` is 4 with ``k``, else 2.
    plus, minus : ndarray, shape (n, M)
        The compared samples ``I(c+s+h)`` and ``I(c+s-h)``.
    """
    window = problem.window
    coeffs, origin = problem.coeffs, problem.origin
    hx, hy = window.offsets[:, 0], window.offsets[:, 1]
    if problem.shift is not None:
        offsets = window.offsets[None]
        centre = c[:, None] + problem.shift
        plus, gu_p, gv_p = spline_sample(coeffs, origin, centre + offsets)
        minus, gu_m, gv_m = spline_sample(coeffs, origin, centre - offsets)
    else:
        size = 2 * window.halfsize + 1
        taps = np.arange(-window.halfsize - 1, window.halfsize + 3)  # interpolation support
        mirror = size * size - 1 - window.keep  # flat index of -h for h at keep
        plus, minus, gu_p, gu_m, gv_p, gv_m = _symmetric_samples(
            coeffs, origin, c, taps, window, mirror
        )
    residual = plus - minus
    jac_u, jac_v = gu_p - gu_m, gv_p - gv_m
    columns = [jac_u, jac_v]
    if k is not None:
        tilt = k[:, 0, None] * hx[None] + k[:, 1, None] * hy[None]
        total = plus + minus
        residual = residual - tilt * total
        columns = [jac_u - tilt * (gu_p + gu_m), jac_v - tilt * (gv_p + gv_m)]
        columns += [-hx[None] * total, -hy[None] * total]
    return residual, np.stack(columns, axis=-1), plus, minus


def _symmetric_samples(
    coeffs: np.ndarray,
    origin: np.ndarray,
    c: np.ndarray,
    taps: np.ndarray,
    window: _Window,
    mirror: np.ndarray,
) -> tuple[np.ndarray, ...]:
    """Values and gradients at ``c + h`` and ``c - h`` for integer offsets, (n, M) each.

    All samples of one corner share the sub-pixel phase of ``c``, so one separable
    4 x 4 interpolation of the whole box serves them.
    """
    box_h, box_w = coeffs.shape
    n = len(c)
    size = 2 * window.halfsize + 1
    base = np.floor(c).astype(int)
    frac = c - base
    rows_ = base[:, 1, None] + taps[None] - origin[1]
    cols_ = base[:, 0, None] + taps[None] - origin[0]
    patch = coeffs[
        np.clip(rows_, 0, box_h - 1)[:, :, None], np.clip(cols_, 0, box_w - 1)[:, None, :]
    ]
    wx, dwx = bspline_weights(frac[:, 0])
    wy, dwy = bspline_weights(frac[:, 1])
    along_x = sum(wx[:, j, None, None] * patch[:, :, j : j + size] for j in range(4))
    slope_x = sum(dwx[:, j, None, None] * patch[:, :, j : j + size] for j in range(4))
    values = sum(wy[:, j, None, None] * along_x[:, j : j + size] for j in range(4))
    grad_v = sum(dwy[:, j, None, None] * along_x[:, j : j + size] for j in range(4))
    grad_u = sum(wy[:, j, None, None] * slope_x[:, j : j + size] for j in range(4))
    values, grad_u, grad_v = (a.reshape(n, -1).astype(np.float64) for a in (values, grad_u, grad_v))
    return (
        values[:, window.keep],
        values[:, mirror],
        grad_u[:, window.keep],
        grad_u[:, mirror],
        grad_v[:, window.keep],
        grad_v[:, mirror],
    )


def symmetric_corners(
    gray: np.ndarray,
    grid: np.ndarray | None,
    start: np.ndarray | None = None,
    *,
    sigma_squares: float = SYMMETRY_SIGMA_SQUARES,
    illumination: bool = True,
    steps: np.ndarray | None = None,
    curvature: np.ndarray | None = None,
) -> SubpixelResult:
    """Refine chessboard corners to the centres of point symmetry of the image.

    Parameters
    ----------
    gray : ndarray, shape (height, width)
        Grey image (any numeric type).
    grid : ndarray, shape (rows, cols, 2), px
        Detected corners in grid order (at least 2 x 2); they give the local square
        size and shape for the window, and the start unless ``start`` is given.
    start : ndarray, shape (rows * cols, 2), px, optional
        Starting points (within about a pixel of the corners).
    sigma_squares : float
        Window sigma in squares (see :data:`SYMMETRY_SIGMA_SQUARES`).
    illumination : bool
        Fit a linear relative illumination gradient per corner (two more unknowns).
    steps : ndarray, shape (n, 2, 2), px, optional
        The local affine map of each corner (as :func:`local_steps` returns it) for
        corners that do not form a full grid (ChArUco); then ``grid`` may be None and
        ``start`` (shape (n, 2)) is required.
    curvature : ndarray, shape (n, 2, 3), px, optional
        The local curvature of the grid map (as :func:`local_quadratic` returns it,
        together with its ``steps``, which must then be given). The compared samples are
        then ``c + h + s(h)`` and ``c - h + s(h)``, ``s`` the second-order displacement
        of the grid map at the board offset ``d = A^-1 h``: the same for ``h`` and ``-h``,
        so the pair still images two board points symmetric about the corner when lens
        distortion curves the grid lines (a plain 180-degree rotation does not).

    Returns
    -------
    SubpixelResult
        ``pixels`` in grid order (``row * cols + col``), or in the order of ``start`` with
        ``steps``, with the start where a corner did not converge.

    Notes
    -----
    The symmetric difference at offset ``h`` is ``r = I(c+h) - I(c-h) - (k.h) S`` with
    ``S = I(c+h) + I(c-h)``; its Jacobian is ``dr/dc = G(c+h) - G(c-h) - (k.h)(G(c+h)
    + G(c-h))`` (``G`` the spline's gradient) and ``dr/dk = -h S``. Each Gauss-Newton
    step solves the 4 x 4 (or 2 x 2) weighted normal equations of every corner at once.
    """
    if steps is None:
        grid = np.asarray(grid, dtype=np.float64)
        steps = local_steps(grid)
        c = grid.reshape(-1, 2).copy() if start is None else np.array(start, dtype=np.float64)
    else:
        if start is None:
            raise ValueError("symmetric_corners with steps needs the start points")
        steps = np.asarray(steps, dtype=np.float64)
        c = np.array(start, dtype=np.float64).reshape(-1, 2)
        if steps.shape != (len(c), 2, 2):
            raise ValueError(f"steps must have shape ({len(c)}, 2, 2), not {steps.shape}")
    start_points = c.copy()
    n = len(c)
    problem = symmetric_problem(gray, c, steps, curvature, sigma_squares)
    weights = problem.weights
    n_unknowns = 4 if illumination else 2
    k = np.zeros((n, 2))
    ok = (weights > 0).sum(axis=1) >= MIN_WINDOW_PAIRS
    settled = np.zeros(n, dtype=bool)
    for _ in range(SYMMETRY_MAX_ITERATIONS):
        residual, jacobian, _, _ = symmetric_system(problem, c, k if illumination else None)
        weighted = jacobian * weights[:, :, None]
        normal = np.matmul(weighted.transpose(0, 2, 1), jacobian)
        gradient = np.matmul(weighted.transpose(0, 2, 1), residual[:, :, None])[..., 0]
        scale = np.trace(normal, axis1=1, axis2=2)[:, None, None]
        singular = ~(scale[:, 0, 0] > 0)
        ridge = 1e-12 * np.where(singular[:, None, None], 1.0, scale) * np.eye(n_unknowns)
        delta = -np.linalg.solve(normal + ridge, gradient[..., None])[..., 0]
        ok &= ~singular & np.isfinite(delta).all(axis=1)
        delta = np.where(ok[:, None], delta, 0.0)
        step = delta[:, :2]
        length = np.linalg.norm(step, axis=1, keepdims=True)
        step = step * np.minimum(1.0, SYMMETRY_MAX_STEP_PX / np.maximum(length, 1e-300))
        c = c + step
        ok &= np.linalg.norm(c - start_points, axis=1) <= SYMMETRY_MAX_SHIFT_PX
        if illumination:
            k = k + delta[:, 2:]
        settled = np.abs(step).max(axis=1) < SYMMETRY_TOLERANCE_PX
        if settled[ok].all():
            break
    converged = ok & settled
    pixels = np.where(converged[:, None], c, start_points)
    return SubpixelResult(pixels, converged)


def saddle_corners(
    gray: np.ndarray,
    grid: np.ndarray,
    start: np.ndarray | None = None,
    *,
    sigma_squares: float = SADDLE_SIGMA_SQUARES,
    iterations: int = 5,
) -> SubpixelResult:
    """Refine chessboard corners to the saddle point of a local quadratic surface.

    Parameters
    ----------
    gray : ndarray, shape (height, width)
    grid : ndarray, shape (rows, cols, 2), px
        Detected corners in grid order; they set the window as in
        :func:`symmetric_corners`.
    start : ndarray, shape (rows * cols, 2), px, optional
    sigma_squares : float
        Window sigma in squares.
    iterations : int
        Re-centring steps (the window follows the estimate).

    Returns
    -------
    SubpixelResult

    Notes
    -----
    Fits ``I = a u^2 + b uv + c v^2 + d u + e v + f`` by weighted least squares on the
    image pre-blurred with a Gaussian of a quarter of the window sigma (a sharp X-junction
    is not quadratic), and moves to its stationary point ``-[[2a, b], [b, 2c]]^-1 (d, e)``
    when that is a saddle (``4ac - b^2 < 0``).
    """
    from scipy.ndimage import gaussian_filter

    grid = np.asarray(grid, dtype=np.float64)
    steps = local_steps(grid)
    c = grid.reshape(-1, 2).copy() if start is None else np.array(start, dtype=np.float64)
    start_points = c.copy()
    n = len(c)
    spacing = np.linalg.svd(steps, compute_uv=False)[:, 1]
    blurred = gaussian_filter(
        np.asarray(gray, dtype=np.float64), max(0.5, 0.25 * sigma_squares * np.median(spacing))
    )
    height, width = blurred.shape
    window = _window(steps, sigma_squares)
    size = 2 * window.halfsize + 1
    span = np.arange(-window.halfsize, window.halfsize + 1)
    hx, hy = np.meshgrid(span, span)
    hx, hy = hx.ravel(), hy.ravel()
    # the full (not half-plane) window: both h and -h
    full = np.concatenate([window.keep, size * size - 1 - window.keep])
    weights = np.concatenate([window.weights, window.weights], axis=1)
    ok = np.ones(n, dtype=bool)
    for _ in range(iterations):
        base = np.round(c).astype(int)
        u = base[:, 0, None] + hx[full][None]
        v = base[:, 1, None] + hy[full][None]
        ok &= (u.min(axis=1) >= 0) & (u.max(axis=1) < width)
        ok &= (v.min(axis=1) >= 0) & (v.max(axis=1) < height)
        values = blurred[np.clip(v, 0, height - 1), np.clip(u, 0, width - 1)]
        du, dv = u - c[:, 0, None], v - c[:, 1, None]
        design = np.stack([du * du, du * dv, dv * dv, du, dv, np.ones_like(du)], axis=-1)
        weighted = design * weights[:, :, None]
        normal = np.matmul(weighted.transpose(0, 2, 1), design)
        rhs = np.matmul(weighted.transpose(0, 2, 1), values[:, :, None])
        ridge = 1e-12 * np.trace(normal, axis1=1, axis2=2)[:, None, None] * np.eye(6)
        coef = np.linalg.solve(normal + ridge, rhs)[..., 0]
        a, b, cc, d, e = (coef[:, i] for i in range(5))
        hessian = np.stack([np.stack([2 * a, b], -1), np.stack([b, 2 * cc], -1)], -2)
        saddle = 4 * a * cc - b * b < 0
        ok &= saddle
        safe = np.where(saddle[:, None, None], hessian, np.eye(2))
        step = -np.linalg.solve(safe, np.stack([d, e], -1)[..., None])[..., 0]
        ok &= np.linalg.norm(step, axis=1) < 2.0
        c = c + np.where(ok[:, None], step, 0.0)
    return SubpixelResult(np.where(ok[:, None], c, start_points), ok)
