"""Does the symmetric fit's formal precision explain the test set's detection noise?

    python bench/corner_precision.py WORK [--max-images N] [--twins K] [--quick]

WORK is the folder of a ``bench/accuracy_report.py --work WORK`` run (its session
``accuracy.h5`` and, with ``--test-seeds``, its merged set ``data/``; otherwise
``sample_sessions/``). For every test image whose board was found in both halves, the
detected corners are compared with the simulator's true corners, and each corner's
formal covariance (:func:`endomeasure.features.precision.symmetric_precision`) is
computed in the half image the detector saw, with two pixel-noise figures: the
simulator's sensor model (shot + read + 8-bit rounding variance per pixel, evaluated at
the pixel's grey level) and the fit's own residuals.

Prints, per board, the empirical standard deviation of the u, v and disparity (left u
minus right u) errors binned by the corner's distance from the image's middle row, its
distance from its half's middle column, its board row and column, the half, the
distance and the local contrast, each bin with its count ``n``, the RMS formal sigma
and the ratio actual / formal. Errors are not de-meaned per image: the per-half mean
error is printed first, and it is what independent noise of 30 corners gives.

With ``--twins K`` it also renders noise-free twins of K test images (the same pose and
exposure through :func:`endomeasure.simulate.render.render`, float grey levels without
rounding), refines their corners from the detected ones and splits each corner's error
into a deterministic part (the twin's error) and the noise part (detected minus twin):
the formal sigma should predict the noise part only.

The refinement is re-linearised at the detected corners with the local quadratic grid
map of the detected grid (the detector used its cornerSubPix starts for it: the window
and curvature differ by a few hundredths of a pixel, a second-order change).

Prints only (a diagnosis; docs/accuracy.md quotes its findings) and has no target;
``--no-write`` is accepted for the common interface. ``--quick``: 4 test images, at most
one twin.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from _common import script_parser  # noqa: E402
from _samples import detection_errors  # noqa: E402
from endomeasure.simulate.manifest import load_manifest, load_truth  # noqa: E402

ROW_BINS = (0, 12, 23, 34, 45, 1000)  # px from the image's middle row
COL_BINS = (0, 20, 40, 60, 1000)  # px from the half's middle column
DISTANCE_BINS = (12, 17, 22, 27, 32, 37, 41)  # mm
CONTRAST_QUANTILES = (0, 1 / 3, 2 / 3, 1)
QUICK_MAX_IMAGES = 4


@dataclass
class Corners:
    """One row per detected corner of the test set (both halves found)."""

    columns: dict[str, list]

    def array(self, name: str) -> np.ndarray:
        return np.asarray(self.columns[name])


def sensor_variance(gray: np.ndarray, sensor: dict) -> np.ndarray:
    """Per-pixel noise variance of the simulator's sensor at the observed grey levels.

    Shot noise (Poisson in electrons), read noise, gain ``255 / full well`` and the 8-bit
    rounding (1/12), as ``simulate/render.py`` applies them; the noisy pixel stands for
    its mean (unbiased for the shot term, which is linear in it).
    """
    gain = 255.0 / float(sensor["full_well_e"])
    signal = np.clip(gray.astype(np.float64) - float(sensor["black_level_dn"]), 0.0, None)
    return gain * signal + (gain * float(sensor["read_noise_e"])) ** 2 + 1.0 / 12.0


def local_contrast(gray: np.ndarray, pixels: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """Grey-level spread (95th minus 5th percentile) in a box of 0.3 squares, (n,)."""
    height, width = gray.shape
    out = np.empty(len(pixels))
    for i, (p, a) in enumerate(zip(pixels, steps, strict=True)):
        half = max(2, int(round(0.3 * np.abs(a).sum(axis=1).max())))
        u, v = np.round(p).astype(int)
        box = gray[
            max(0, v - half) : min(height, v + half + 1),
            max(0, u - half) : min(width, u + half + 1),
        ]
        out[i] = np.percentile(box, 95) - np.percentile(box, 5)
    return out


def collect(work: Path, max_images: int | None) -> tuple[Corners, list[float]]:
    import cv2

    from endomeasure.features.precision import symmetric_precision
    from endomeasure.features.subpixel import local_quadratic

    data = work / "data" if (work / "data").exists() else ROOT / "sample_sessions"
    manifest = load_manifest(data)
    split = int(manifest["split"])
    height = manifest["image_size"][1]
    sensor = manifest["preset_data"]["sensor"]
    by_image: dict[str, dict] = {}
    for h in detection_errors(data, work / "accuracy.h5", sets=("test",)):
        if h.found:
            by_image.setdefault(h.image, {})[h.half] = h
    images = [name for name, halves in by_image.items() if len(halves) == 2]
    if max_images:
        images = images[:: max(1, len(images) // max_images)][:max_images]
    cols: dict[str, list] = {k: [] for k in (
        "image", "board", "half", "id", "row", "col", "distance", "dv", "du", "eu", "ev",
        "su", "sv", "corr", "su_res", "sv_res", "contrast", "var_model", "var_res",
    )}  # fmt: skip
    half_means = []
    for name in images:
        truth = load_truth(data, name)
        item = next(i for i in manifest["sets"]["test"]["images"] if Path(i["image"]).stem == name)
        gray_full = cv2.imread(str(data / item["image"]), cv2.IMREAD_GRAYSCALE)
        noise_full = sensor_variance(gray_full, sensor)
        square = truth["board_spec"]
        for half_name, h in by_image[name].items():
            lo, hi = (0, split) if half_name == "left" else (split, gray_full.shape[1])
            gray = np.ascontiguousarray(gray_full[:, lo:hi])
            noise = np.ascontiguousarray(noise_full[:, lo:hi])
            pixels = h.detected - [lo, 0]
            rows = int(h.ids.size // h.cols)
            grid = pixels.reshape(rows, h.cols, 2)
            steps, curvature = local_quadratic(grid)
            model = symmetric_precision(gray, pixels, steps, curvature, noise=noise)
            residual = symmetric_precision(gray, pixels, steps, curvature, noise=None)
            errors = h.errors
            half_means.append(np.abs(errors.mean(axis=0)))
            n = len(pixels)
            cols["image"] += [name] * n
            cols["board"] += [square] * n
            cols["half"] += [half_name] * n
            cols["id"] += list(h.ids)
            cols["row"] += list(h.ids // h.cols)
            cols["col"] += list(h.ids % h.cols)
            cols["distance"] += [float(truth["distance_mm"])] * n
            cols["dv"] += list(np.abs(h.detected[:, 1] - (height - 1) / 2.0))
            cols["du"] += list(np.abs(pixels[:, 0] - (hi - lo - 1) / 2.0))
            cols["eu"] += list(errors[:, 0])
            cols["ev"] += list(errors[:, 1])
            cols["su"] += list(model.sigma[:, 0])
            cols["sv"] += list(model.sigma[:, 1])
            cols["corr"] += list(model.corr_uv)
            cols["su_res"] += list(residual.sigma[:, 0])
            cols["sv_res"] += list(residual.sigma[:, 1])
            cols["var_model"] += list(model.noise_variance)
            cols["var_res"] += list(residual.noise_variance)
            cols["contrast"] += list(local_contrast(gray, pixels, steps))
    return Corners(cols), half_means


def twins(work: Path, count: int) -> None:
    """Errors of noise-free twins against the noisy detections (see the module doc)."""
    import dataclasses

    from endomeasure.features.precision import symmetric_precision
    from endomeasure.features.subpixel import local_quadratic, symmetric_corners
    from endomeasure.simulate.preset import load_preset
    from endomeasure.simulate.render import render
    from endomeasure.simulate.targets import target_from_preset

    data = work / "data"
    manifest = load_manifest(data)
    split, height = int(manifest["split"]), manifest["image_size"][1]
    preset = load_preset(manifest["preset"]["name"])
    by_image: dict[str, dict] = {}
    for h in detection_errors(data, work / "accuracy.h5", sets=("test",)):
        if h.found:
            by_image.setdefault(h.image, {})[h.half] = h
    names = sorted(n for n, halves in by_image.items() if len(halves) == 2)
    names = names[:: max(1, len(names) // count)][:count]
    rows = []
    for name in names:
        truth = load_truth(data, name)
        pose = np.array(truth["T_camera_board"]["matrix"])
        target = target_from_preset(
            truth["target"]["name"], preset.targets[truth["target"]["name"]]
        )
        target = dataclasses.replace(target, R=pose[:3, :3], t=pose[:3, 3])
        rendering = render(
            preset, target, noise_free=True, exposure=float(truth["render"]["exposure"])
        )
        grey = float(preset.sensor["black_level_dn"]) + rendering.radiance * 255.0
        for half_name, h in by_image[name].items():
            lo, hi = (0, split) if half_name == "left" else (split, grey.shape[1])
            pixels = h.detected - [lo, 0]
            steps, curvature = local_quadratic(pixels.reshape(-1, h.cols, 2))
            twin = symmetric_corners(
                np.ascontiguousarray(grey[:, lo:hi]), None, pixels, steps=steps, curvature=curvature
            )
            formal = symmetric_precision(
                np.ascontiguousarray(grey[:, lo:hi]), twin.pixels, steps, curvature,
                noise=sensor_variance(np.clip(np.rint(grey[:, lo:hi]), 0, 255), preset.sensor),
            )  # fmt: skip
            deterministic = twin.pixels + [lo, 0] - h.true_pixels[h.ids]
            noise = h.detected - twin.pixels - [lo, 0]
            dv = np.abs(h.detected[:, 1] - (height - 1) / 2.0)
            for i in range(len(pixels)):
                rows.append(
                    (
                        truth["board_spec"],
                        dv[i],
                        *h.errors[i],
                        *deterministic[i],
                        *noise[i],
                        *formal.sigma[i],
                    )
                )
    print(
        f"\nnoise-free twins of {len(names)} test images: std of the detected error, of the twin's"
        " (deterministic) error, of detected minus twin (noise) and RMS formal sigma, px"
    )
    spec = np.array([r[0] for r in rows])
    r = np.array([r[1:] for r in rows], dtype=float)
    for board in sorted(set(spec)):
        for lo, hi in zip(ROW_BINS[:-1], ROW_BINS[1:], strict=True):
            inside = (spec == board) & (r[:, 0] >= lo) & (r[:, 0] < hi)
            if inside.sum() < 10:
                continue
            x = r[inside]
            cells = []
            for axis, name in ((0, "u"), (1, "v")):
                corr = np.corrcoef(x[:, 1 + axis], x[:, 3 + axis])[0, 1]
                cells.append(
                    f"{name}: detected {x[:, 1 + axis].std():.4f}, twin {x[:, 3 + axis].std():.4f}"
                    f" (corr {corr:+.2f}), noise {x[:, 5 + axis].std():.4f} / formal"
                    f" {np.sqrt(np.mean(x[:, 7 + axis] ** 2)):.4f}"
                )
            print(
                f"  {board} |v - middle row| {lo}-{hi} px, n={int(inside.sum())}: "
                + " | ".join(cells)
            )


def disparity_rows(c: Corners) -> dict[str, np.ndarray]:
    """Per corner seen in both halves: disparity error and its formal sigmas."""
    key = [f"{i}|{j}" for i, j in zip(c.array("image"), c.array("id"), strict=True)]
    half = c.array("half")
    left = {k: n for n, k in enumerate(key) if half[n] == "left"}
    right = {k: n for n, k in enumerate(key) if half[n] == "right"}
    both = [(left[k], right[k]) for k in left if k in right]
    li, ri = np.array(both).T
    eu, su, sr = c.array("eu"), c.array("su"), c.array("su_res")
    out = {
        name: c.array(name)[li] for name in ("board", "row", "col", "distance", "dv", "contrast")
    }
    out["du"] = c.array("du")[li]
    out["half"] = np.full(len(li), "both")
    out["e"] = eu[li] - eu[ri]
    out["s"] = np.hypot(su[li], su[ri])
    out["s_res"] = np.hypot(sr[li], sr[ri])
    return out


def table(title: str, x: np.ndarray, edges, series, select: np.ndarray) -> None:
    """Print std, RMS formal sigma and their ratio per bin of x."""
    print(f"  by {title}:")
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        inside = (
            select & (x >= lo) & (x < hi) if hi != edges[-1] else select & (x >= lo) & (x <= hi)
        )
        n = int(inside.sum())
        if n < 10:
            continue
        parts = []
        for name, e, s, s_res in series:
            actual = e[inside].std()
            formal = np.sqrt(np.mean(s[inside] ** 2))
            formal_res = np.sqrt(np.mean(s_res[inside] ** 2))
            ratio, ratio_res = actual / formal, actual / formal_res
            parts.append(
                f"{name} {actual:.4f} / {formal:.4f} = {ratio:4.2f} (res {ratio_res:4.2f})"
            )
        print(f"    {lo:6.4g}-{hi:<6.4g} n={n:5d}  " + " | ".join(parts))


def main(argv: list[str] | None = None) -> int:
    ap = script_parser(__doc__)
    ap.add_argument("work", type=Path, help="the --work folder of bench/accuracy_report.py")
    ap.add_argument("--max-images", type=int, default=None, help="test images to use (all)")
    ap.add_argument(
        "--twins", type=int, default=0, help="noise-free twins to render (about 2 s each)"
    )
    args = ap.parse_args(argv)
    if args.quick:
        args.max_images, args.twins = QUICK_MAX_IMAGES, min(args.twins, 1)
    c, half_means = collect(args.work, args.max_images)
    m = np.array(half_means)
    mean_u, mean_v = np.sqrt(np.mean(m**2, axis=0))
    print(
        f"{len(m)} halves, {len(c.array('eu'))} corners; per-half mean error RMS u {mean_u:.4f},"
        f" v {mean_v:.4f} px (independent noise of 30 corners gives std / 5.5);"
        " errors are used as they are (no per-image de-meaning)"
    )
    print(
        "cells: actual std / RMS formal sigma (sensor-model noise) = ratio (res: ratio with"
        " the residual-estimated noise), px"
    )
    board = c.array("board")
    series = [
        ("u", c.array("eu"), c.array("su"), c.array("su_res")),
        ("v", c.array("ev"), c.array("sv"), c.array("sv_res")),
    ]
    disp = disparity_rows(c)
    for spec in sorted(set(board)):
        sel = board == spec
        var_model, var_res = c.array("var_model")[sel], c.array("var_res")[sel]
        print(
            f"\n{spec}: pixel noise variance in the windows, median: sensor model "
            f"{np.median(var_model):.2f}, fit residuals {np.median(var_res):.2f} grey levels^2;"
            f" formal corr_uv median {np.median(c.array('corr')[sel]):+.2f}"
        )
        contrast = c.array("contrast")
        edges = np.quantile(contrast[sel], CONTRAST_QUANTILES)
        for title, x, bins in (
            ("|v - middle row| px", c.array("dv"), ROW_BINS),
            ("|u - half's middle column| px", c.array("du"), COL_BINS),
            ("board row", c.array("row"), np.arange(0, 6) - 0.5),
            ("board column", c.array("col"), np.arange(0, 7) - 0.5),
            ("distance mm", c.array("distance"), DISTANCE_BINS),
            ("local contrast (grey levels)", contrast, edges),
        ):
            table(title, x, bins, series, sel)
        for half_name in ("left", "right"):
            table(
                f"half = {half_name} (all)",
                np.zeros(sel.size),
                (0, 0),
                series,
                sel & (c.array("half") == half_name),
            )
        dsel = disp["board"] == spec
        dseries = [("disparity", disp["e"], disp["s"], disp["s_res"])]
        print(f"  disparity (left u error minus right u error), {int(dsel.sum())} corners:")
        table("|v - middle row| px", disp["dv"], ROW_BINS, dseries, dsel)
        table("distance mm", disp["distance"], DISTANCE_BINS, dseries, dsel)
    if args.twins:
        twins(args.work, args.twins)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
