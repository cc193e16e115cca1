"""The renderer: per-pixel backward ray tracing through the ground-truth optics.

For every pixel, ``n x n`` sub-pixel rays (an N-rooks pattern centred on the pixel
centre, see :func:`~endomeasure.simulate.optics.sample_offsets`) are traced backwards
through the truth lens and prism (cached per preset) and meet the scene object or a dim
background plane. Each sample's radiance is

    L = albedo * E + specular,   E = sum_k I(phi_k) max(n . l_k, 0) / r_k^2

for the light-guide exits ``k`` of the probe tip (emission lobe ``I = cos^m phi``
about the probe axis, inverse-square fall-off), with a Blinn-Phong term for metal.
Then, in this order:

1. defocus and pixel: the sensor integrates the PSF-blurred radiance over each pixel's
   box, so a pixel is ``(L * G * box)`` at its centre. Every sample is spread with its
   own kernel ``(G * box)(k - y)`` (``y`` the sample's exact sub-pixel position; a
   separable difference of normal CDFs per axis), a Gaussian PSF whose sigma grows with
   the distance from best focus, per pixel (blend of a few uniformly blurred images),
   each half on its own. (Blurring the pixels' sample means with a sampled Gaussian
   instead would integrate the PSF with one point per pixel, an error that depends on
   where an edge falls in its pixel; ``docs/accuracy.md``, "The renderer's pixel
   kernel".)
2. vignetting ``cos^e`` of the lens-space field angle;
3. the dark band the out-of-focus prism apex casts between the halves;
4. auto-exposure (a percentile of the signal to a fraction of the full well), shot
   noise (Poisson), read noise (Gaussian), gain to 8 bits, black level, rounding.

``noise_free`` skips step 4's noise but still quantises to 8 bits.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from endomeasure.simulate.optics import Region, apex_columns, ray_bundle, sample_offsets
from endomeasure.simulate.preset import Preset

__all__ = ["Rendering", "render", "apex_profile", "pixel_kernel"]

_APEX_ROWS = 17  # rows at which the apex image column is solved; linear in between
_BLUR_STEP_PX = 0.05  # spacing of the blur levels blended per pixel (sigma, px)
_KERNEL_REACH_SIGMAS = 4.0  # the pixel kernel reaches this many sigmas beyond the pixel box


class Rendering(NamedTuple):
    """One rendered image and what went into it."""

    image: np.ndarray  # (H, W) uint8
    radiance: np.ndarray  # (H, W) float64: noise-free signal, fraction of full well
    depth: np.ndarray  # (H, W) float64: mean z of the surfaces a pixel sees, mm
    exposure: float  # multiplier from scene radiance to fraction of full well
    region: Region


def apex_profile(preset: Preset, region: Region) -> np.ndarray:
    """Transmission of the apex band over a region, shape (H, W), in (0, 1].

    ``1 - depth exp(-(u - u_apex(v))^2 / (2 sigma^2))`` with ``u_apex(v)`` the image of
    the apex line (solved at a few rows, linear in between) and ``sigma`` a quarter of the
    apex's defocus blur diameter (the apex is 2 mm from a lens focused at 16 mm).
    """
    height = preset.image_size[1]
    rows = np.linspace(0.0, height - 1.0, _APEX_ROWS)
    cols = apex_columns(preset.truth_optics, rows)
    ok = np.isfinite(cols)
    v = np.arange(region.v0, region.v1, dtype=np.float64)
    u_apex = np.interp(v, rows[ok], cols[ok])
    u = np.arange(region.u0, region.u1, dtype=np.float64)
    sigma = preset.apex_band_sigma_px
    depth = float(preset.prism["apex_band_depth"])
    return 1.0 - depth * np.exp(-0.5 * ((u[None, :] - u_apex[:, None]) / sigma) ** 2)


def _irradiance(light: dict, p: tuple, n: tuple) -> tuple[np.ndarray, tuple]:
    """Irradiance from the probe-tip light sources and the unit light directions.

    Parameters
    ----------
    light : dict
        The preset's ``illumination`` section.
    p, n : tuple of 3 ndarray, shape (M,)
        Surface points (mm) and unit normals facing the camera.

    Returns
    -------
    list of (irradiance (M,), (lx, ly, lz)) per source.
    """
    m = float(light["lobe_exponent"])
    out = []
    for sx, sy, sz in np.asarray(light["sources_mm"], dtype=np.float64):
        lx, ly, lz = sx - p[0], sy - p[1], sz - p[2]
        r2 = lx * lx + ly * ly + lz * lz
        inv_r = 1.0 / np.sqrt(r2)
        lx, ly, lz = lx * inv_r, ly * inv_r, lz * inv_r
        emit = np.clip(-lz, 0.0, None) ** m  # emission lobe cos^m about +z, the probe axis
        cos_in = np.clip(n[0] * lx + n[1] * ly + n[2] * lz, 0.0, None)
        out.append((emit * cos_in / r2, (lx, ly, lz)))
    return out


def _shade(preset: Preset, target, o: tuple, d: tuple, valid: np.ndarray):
    """Sample radiance and pixel depth of a block of sample rays.

    Parameters
    ----------
    o, d : tuple of 3 ndarray, shape (N,), float32
        Sample ray origins and directions, ``N = h * W * S``.
    valid : ndarray of bool, shape (h, W, S)

    Returns
    -------
    radiance : ndarray, shape (h, W, S)
        Per sample (0 where the ray failed).
    depth : ndarray, shape (h, W)
        Mean z of the surfaces the pixel's samples see, mm.

    Notes
    -----
    Hits and albedo are evaluated per sample (that is what anti-aliases edges); the
    illumination, smooth at the scale of a pixel, is evaluated once per pixel for the
    samples on the target (at their mean point and normal) and once for those on the
    background. The error of this split is second order in the irradiance change
    across one pixel (below 1e-3 px of edge position).
    """
    shape = valid.shape
    hit = target.hit(o, d)
    light = preset.illumination
    z_bg = float(light["background_mm"])
    on = hit.hit.reshape(shape) & valid
    bg = ~hit.hit.reshape(shape) & valid
    t = hit.t
    miss = ~hit.hit
    t[miss] = (z_bg - o[2][miss]) / d[2][miss]
    p = [(o[k] + t * d[k]).reshape(shape) for k in range(3)]
    n_on = on.sum(-1)
    n_bg = bg.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        p_on = tuple(np.where(on, pk, 0).sum(-1) / n_on for pk in p)
        p_bg = tuple(np.where(bg, pk, 0).sum(-1) / n_bg for pk in p)
        depth = (np.where(on, p[2], 0).sum(-1) + np.where(bg, p[2], 0).sum(-1)) / (n_on + n_bg)
        normal = []
        for nk in hit.normal:
            if np.ndim(nk):
                normal.append(np.where(on, nk.reshape(shape), 0).sum(-1) / n_on)
            else:
                normal.append(np.full(n_on.shape, float(nk)))
        norm = np.sqrt(sum(nk * nk for nk in normal))
        normal = tuple(nk / norm for nk in normal)
        view = [np.where(on, dk.reshape(shape), 0).sum(-1) for dk in d]
    albedo = np.where(on, hit.albedo.reshape(shape), 0.0)
    irradiance_on = np.zeros(n_on.shape)  # per pixel, multiplies each sample's albedo
    specular_on = np.zeros(n_on.shape)  # per pixel, added to each sample on the target
    specular = float(hit.specular)
    shininess = float(getattr(target, "shininess", 1.0))
    has_on = n_on > 0
    if has_on.any():
        vnorm = np.sqrt(sum(v * v for v in view))
        for irradiance, (lx, ly, lz) in _irradiance(light, p_on, normal):
            irradiance_on += np.where(has_on, irradiance, 0.0)
            if specular > 0:
                hx, hy, hz = (lk - v / vnorm for lk, v in zip((lx, ly, lz), view, strict=True))
                cos_h = np.clip(normal[0] * hx + normal[1] * hy + normal[2] * hz, 0, None)
                cos_h /= np.sqrt(hx * hx + hy * hy + hz * hz)
                specular_on += np.where(has_on, specular * irradiance * cos_h**shininess, 0.0)
    irradiance_bg = np.zeros(n_on.shape)
    has_bg = n_bg > 0
    if has_bg.any():
        zero = np.zeros_like(irradiance_bg)
        flat = (zero, zero, -np.ones_like(irradiance_bg))
        for irradiance, _ in _irradiance(light, p_bg, flat):
            irradiance_bg += np.where(has_bg, irradiance, 0.0)
    irradiance_bg *= float(light["background_albedo"])
    radiance = albedo * irradiance_on[..., None] + np.where(on, specular_on[..., None], 0.0)
    radiance += np.where(bg, irradiance_bg[..., None], 0.0)
    radiance[~np.isfinite(radiance)] = 0.0
    depth = np.where(np.isfinite(depth), depth, z_bg)
    return radiance, depth


def pixel_kernel(sigma: float, offset: float) -> np.ndarray:
    """One axis of the pixel kernel: the Gaussian PSF convolved with the pixel's box.

    A point of unit flux at ``offset`` px from the centre of pixel 0 blurred by a Gaussian
    of standard deviation ``sigma`` puts into pixel ``m`` (which covers ``m - 0.5 <= x <
    m + 0.5``) the fraction ``Phi((m + 0.5 - offset) / sigma) - Phi((m - 0.5 - offset) /
    sigma)``.

    Parameters
    ----------
    sigma : float
        PSF standard deviation, px (0 gives the box alone).
    offset : float
        Sub-pixel position of the point, px, in ``[-0.5, 0.5)``.

    Returns
    -------
    ndarray, shape (2 r + 1,)
        The fractions for ``m = -r .. r``, ``r = ceil(4 sigma + 1)``, normalised to sum 1
        (the cut tails hold below 1e-4 of the flux).
    """
    from scipy.special import ndtr

    reach = int(np.ceil(_KERNEL_REACH_SIGMAS * sigma + 1.0))
    m = np.arange(-reach, reach + 1, dtype=np.float64)
    if sigma > 0:
        w = ndtr((m + 0.5 - offset) / sigma) - ndtr((m - 0.5 - offset) / sigma)
    else:
        w = ((m - 0.5 <= offset) & (offset < m + 0.5)).astype(np.float64)
    return w / w.sum()


def _blur_half(samples: np.ndarray, offsets: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Pixels of the PSF-blurred image from sub-pixel samples, spatially varying PSF.

    Parameters
    ----------
    samples : ndarray, shape (H, W, S)
        Radiance of each pixel's samples.
    offsets : ndarray, shape (S, 2), px
        Sample offsets ``(du, dv)`` from the pixel centre (the same in every pixel).
    sigma : ndarray, shape (H, W), px
        PSF sigma per output pixel.

    Returns
    -------
    ndarray, shape (H, W)
        ``sum_s (G * box)(k - y_s) L_s / S`` per pixel ``k``: each sample spread with the
        pixel kernel at its own sub-pixel position (a separable filter per sample), at a
        few uniform sigmas blended linearly per output pixel.
    """
    from scipy.ndimage import correlate1d

    lo, hi = float(sigma.min()), float(sigma.max())
    n_levels = max(2, int(np.ceil((hi - lo) / _BLUR_STEP_PX)) + 1)
    levels = np.linspace(lo, hi, n_levels) if hi > lo else np.array([lo, lo + 1e-9])
    pos = np.clip((sigma - levels[0]) / (levels[1] - levels[0]), 0, n_levels - 1 - 1e-9)
    k = np.floor(pos).astype(np.int64)
    w = pos - k
    out = np.zeros(samples.shape[:2])
    for level in range(n_levels):
        weight = np.where(k == level, 1.0 - w, 0.0) + np.where(k + 1 == level, w, 0.0)
        if not weight.any():
            continue
        blurred = np.zeros(samples.shape[:2])
        for s, (du, dv) in enumerate(offsets):
            # out[k] = sum_m kernel(m) L[k - m]: a convolution, i.e. correlation with the
            # reversed kernel
            along_u = correlate1d(
                samples[:, :, s], pixel_kernel(levels[level], du)[::-1], axis=1, mode="nearest"
            )
            blurred += correlate1d(
                along_u, pixel_kernel(levels[level], dv)[::-1], axis=0, mode="nearest"
            )
        out += weight * blurred / len(offsets)
    return out


def render(
    preset: Preset,
    target,
    *,
    rng: np.random.Generator | None = None,
    noise_free: bool = False,
    region: Region | None = None,
    exposure: float | None = None,
) -> Rendering:
    """Render one image of a posed target through the preset's ground-truth optics.

    Parameters
    ----------
    preset : Preset
    target : Chessboard or MetalCylinder
        The posed scene object.
    rng : numpy Generator, optional
        Source of the sensor noise; required unless ``noise_free``.
    noise_free : bool
        Skip shot and read noise (the image is still quantised to 8 bits).
    region : Region, optional
        Render only this rectangle of the image (full-image pixel indices); the default
        is the whole image. Blur and noise are computed inside the region.
    exposure : float, optional
        Fixed multiplier from radiance to fraction of full well; by default chosen so
        that the ``exposure_percentile`` of the region's signal reaches
        ``exposure_target`` (the probe's auto-exposure).

    Returns
    -------
    Rendering
    """
    if not noise_free and rng is None:
        raise ValueError("a noisy render needs an rng (or noise_free=True)")
    region = region or Region.full(preset.image_size)
    model = preset.truth_optics
    bundle = ray_bundle(model, region, preset.supersampling, preset.chunk_rays)
    H, W, S = bundle.valid.shape
    signal = np.zeros((H, W, S))
    depth = np.zeros((H, W))
    rows_per_chunk = max(1, preset.chunk_rays // (W * S))
    for r0 in range(0, H, rows_per_chunk):
        r1 = min(H, r0 + rows_per_chunk)
        o = tuple(bundle.origins[k, r0:r1].reshape(-1) for k in range(3))
        d = tuple(bundle.directions[k, r0:r1].reshape(-1) for k in range(3))
        # failed rays (zero vectors) make NaN on the way; they are masked by ``valid``
        with np.errstate(invalid="ignore", divide="ignore"):
            signal[r0:r1], depth[r0:r1] = _shade(preset, target, o, d, bundle.valid[r0:r1])

    # 1. defocus + lens PSF and the pixel box, each half separately (light does not
    # cross the apex)
    sigma = preset.blur_sigma_px(depth)
    offsets = sample_offsets(preset.supersampling)
    split = model.config.split
    cols = np.arange(region.u0, region.u1)
    blurred = np.empty((H, W))
    for mask in (cols < split, cols >= split):
        if mask.any():
            blurred[:, mask] = _blur_half(signal[:, mask], offsets, sigma[:, mask])
    # 2. vignetting, 3. apex band
    blurred *= bundle.cos_lens ** float(preset.lens["vignetting_exponent"])
    blurred *= apex_profile(preset, region)

    # 4. exposure, noise, 8 bits
    sensor = preset.sensor
    if exposure is None:
        seen = bundle.valid.any(-1)
        level = (
            np.percentile(blurred[seen], float(sensor["exposure_percentile"])) if seen.any() else 0
        )
        exposure = float(sensor["exposure_target"]) / level if level > 0 else 1.0
    fraction = blurred * exposure
    full_well = float(sensor["full_well_e"])
    electrons = fraction * full_well
    if not noise_free:
        electrons = rng.poisson(np.clip(electrons, 0.0, None)).astype(np.float64)
        electrons += rng.normal(0.0, float(sensor["read_noise_e"]), size=electrons.shape)
    dn = float(sensor["black_level_dn"]) + electrons * (255.0 / full_well)
    image = np.clip(np.rint(dn), 0, 255).astype(np.uint8)
    return Rendering(image, fraction, depth, float(exposure), region)
