"""The shift precision a window's texture allows, from the simulator's noise-free render.

An independent check of the dense search's precision gate (docs/surface.md, "The
coverage bound"): for each scene image of the demo session (and with ``--designs`` of
random designs, as ``bench/accuracy_dense.py``) the same posed scene is rendered without
noise, and every counted left pixel gets the Fisher information of a window's shift
along the true epipolar direction: per pixel ``g^2 / (var_L + var_R)``, ``g`` the
noise-free right half's derivative along the direction the true match moves with depth
(truth optics), the variances the sensor's shot, read and 8-bit quantisation noise in
electrons; summed over the window once the window has lost its mean and plane, as the
correlation does. Its inverse square root is the Cramér-Rao bound for a known texture.
An unknown texture adds a low-signal term, the noise of the searched half's derivative:
``measure.correspondence.match_precision``'s second-order factor, here on the noise-free
energy. Against both: the matcher's own predicted precision at the true surface
(``gates_at`` with that window alone). Prints the medians over the counted pixels;
writes nothing.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "src"))

from _common import scene_options, script_parser  # noqa: E402
from accuracy_dense import _true_surface, _truth, scene_frames, true_right  # noqa: E402

DEPTH_STEP = 1e-3
"""Relative step along the left ray that gives the true match's direction of motion."""


class Texture(NamedTuple):
    """One frame's medians over its counted pixels, px, per window side."""

    label: str
    known: dict  # window -> Cramér-Rao bound, known texture
    unknown: dict  # window -> with the low-signal term of an unknown texture
    matcher: dict  # window -> gates_at's predicted precision at the true surface
    passed: dict  # window -> share of counted pixels each of the three allows at the gate


def _window_sums(values: list[np.ndarray], window: int) -> list[np.ndarray]:
    import cv2

    return [cv2.boxFilter(v, -1, (window, window), normalize=False,
                          borderType=cv2.BORDER_CONSTANT) for v in values]  # fmt: skip


def detrended_energy(g: np.ndarray, mask: np.ndarray, window: int):
    """Window sums of ``g``'s square after each window's least-squares plane in (u, v)
    is removed (over the ``mask`` pixels only), and the number of those pixels."""
    h, w = g.shape
    g, m = np.where(mask, g, 0.0), mask.astype(np.float64)
    # coordinates about the frame's centre keep the normal equations well scaled
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    uu, vv = uu - w / 2, vv - h / 2
    n, su, sv, suu, svv, suv, sg, sgu, sgv, sgg = _window_sums(
        [m, m * uu, m * vv, m * uu * uu, m * vv * vv, m * uu * vv, g, g * uu, g * vv, g * g],
        window,
    )
    normal = np.stack([np.stack([n, su, sv], -1), np.stack([su, suu, suv], -1),
                       np.stack([sv, suv, svv], -1)], -2)  # fmt: skip
    rhs = np.stack([sg, sgu, sgv], -1)
    fit = n > 3
    explained = np.zeros(g.shape)
    solved = np.linalg.pinv(normal[fit]) @ rhs[fit][..., None]
    explained[fit] = np.einsum("ki,ki->k", solved[..., 0], rhs[fit])
    return np.where(fit, np.maximum(sgg - explained, 0.0), 0.0), n


def texture_frame(label, cm, preset, target, image, settings) -> Texture:
    """The three precisions of every window side of the ladder over one frame."""
    import dataclasses

    from scipy.ndimage import map_coordinates

    from endomeasure.interpolation import noise_transfer
    from endomeasure.measure.dense import gates_at
    from endomeasure.simulate.render import render

    truth = _truth(cm.model, preset, target)
    split = cm.model.config.split
    further, seen = true_right(preset, truth.depth, 1.0 + DEPTH_STEP)
    both = truth.both & seen
    along = further - truth.right
    along /= np.linalg.norm(along, axis=-1, keepdims=True)

    clean = render(preset, target, noise_free=True)
    sensor = preset.sensor
    full_well, read = float(sensor["full_well_e"]), float(sensor["read_noise_e"])
    electrons = clean.radiance * full_well
    floor = read**2 + (full_well / 255.0) ** 2 / 12.0  # read noise and quantisation, e^2
    dy, dx = np.gradient(electrons)

    def at_right(values):
        out = np.zeros(both.shape)
        rows, cols = truth.right[both][:, 1], truth.right[both][:, 0]
        out[both] = map_coordinates(values, [rows, cols], order=1)
        return out

    g = at_right(dx) * along[..., 0] + at_right(dy) * along[..., 1]
    var_r = at_right(electrons) + floor
    var_both = electrons[:, :split] + floor + var_r
    clipped = (clean.image[:, :split] >= 255) | (at_right(clean.image.astype(float)) >= 254.5)
    usable = both & ~clipped
    derivative_noise = noise_transfer().derivative
    inverse = _true_surface(cm.model, truth.z_model)
    limit = settings.max_precision_px

    known, unknown, matcher, passed = {}, {}, {}, {}
    for side in settings.windows():
        energy, n = detrended_energy(g, usable, side)
        # the window's mean variances (the per-pixel ones vary slowly over a window)
        mean_both, mean_r = (s / np.maximum(n, 1) for s in
                             _window_sums([np.where(usable, var_both, 0.0),
                                           np.where(usable, var_r, 0.0)], side))  # fmt: skip
        with np.errstate(divide="ignore", invalid="ignore"):
            crb = np.sqrt(mean_both / energy)
            second = side * side * derivative_noise * mean_r / energy
            low_signal = crb * np.sqrt(1.0 + second)
        alone = dataclasses.replace(settings, window_range_px=(side, side), prefilter_px=0.0)
        precision = gates_at(cm.model, image, inverse, None, alone).precision_px
        known[side], unknown[side], matcher[side] = (
            float(np.nanmedian(np.where(both, x, np.nan))) for x in (crb, low_signal, precision)
        )
        passed[side] = tuple(100 * float(np.mean(x[both] <= limit))
                             for x in (crb, low_signal, precision))  # fmt: skip
    return Texture(label, known, unknown, matcher, passed)


def main() -> int:
    parser = script_parser(__doc__)
    scene_options(parser)
    args = parser.parse_args()
    from endomeasure.measure.dense import DenseSettings
    from endomeasure.pipeline import search_depths

    def settings_for(cm):
        return DenseSettings(depth_range_mm=search_depths(cm))

    default, design = scene_frames(args, settings_for, texture_frame)
    frames = default + design
    sides = list(frames[0].known) if frames else []
    print("Median shift precision over the counted pixels, px (and the share of them at or "
          "below the precision gate, %): the Cramér-Rao bound for a known texture / with "
          "an unknown texture's low-signal term / the matcher's prediction at the true "
          "surface.\n")  # fmt: skip
    print("| frame | " + " | ".join(f"{s} px window" for s in sides) + " |")
    print("|---|" + "---|" * len(sides))
    for f in frames:
        cells = [f"{f.known[s]:.3f} / {f.unknown[s]:.3f} / {f.matcher[s]:.3f} "
                 f"({f.passed[s][0]:.0f} / {f.passed[s][1]:.0f} / {f.passed[s][2]:.0f} %)"
                 for s in sides]  # fmt: skip
        print(f"| {f.label} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
