"""The model-error term on the random designs: does the +- follow a calibration's misfit?

    .venv/bin/python bench/misfit_designs.py WORK [--designs 1-40] [--default SESSION]
                                             [--no-write]

WORK is the folder of a ``bench/accuracy_designs.py --work WORK`` run (each design's
calibrated session ``design_NNN.h5``). For every design whose raytrace calibration is
usable: the misfit its residuals show beyond noise (:mod:`endomeasure.solvers.misfit`,
measured when the model is loaded), and its board test predicted by ``predict-error
--board-test``'s defaults with the model-error term and without it
(``--no-model-error``): the share of the errors inside the predicted 2-sigma band and the
zones with n >= 30 whose actual std is within +-25 % of the predicted one. ``--default
SESSION`` adds a calibrated session of the default preset (e.g. ``make demo``'s
``out/demo/demo.h5``), its raytrace and, as a stress case far beyond what a usable
calibration holds, its pinhole pair (whose calibration fails its verdict, so that
``measure`` refuses it; predicted here anyway).

Each design's figures go to ``WORK/misfit_designs.jsonl`` as it finishes (a rerun reuses
them; ``--fresh`` recomputes). Writes the "misfit-designs" section of docs/accuracy.md
unless ``--no-write``.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from _common import ACCURACY, Report, parse_seeds  # noqa: E402
from accuracy_designs import (  # noqa: E402
    MIN_ZONE_N,
    STD_RATIO_LIMIT,
    _finished,
    store_design,
    stored_designs,
    work_parser,
)

SECTION = "misfit-designs"
SIGNIFICANT = 0.5
"""A design whose misfit RMS reaches this fraction of its noise RMS is listed apart: below
it the term changes the +- by at most some 12 %."""


def misfit_figures(session: Path, model: str = "raytrace", allow_failed: bool = False):
    """The misfit of ``model`` in ``session`` and its board test predicted with and
    without the model-error term; None when the model is not usable."""
    from endomeasure import defaults
    from endomeasure.errors import EndomeasureError
    from endomeasure.io.session import open_session
    from endomeasure.measure.board_runs import prediction_zones, within_band
    from endomeasure.pipeline import calibrated_model
    from endomeasure.pipeline.predict import (
        NoiseAssumptions,
        _board_test_of,
        board_predictions,
        board_test_noise,
    )

    with tempfile.TemporaryDirectory() as tmp:  # a new board test is not stored
        copy = Path(tmp) / session.name
        shutil.copy(session, copy)
        with open_session(copy) as reader:
            try:
                cm = calibrated_model(reader, model, copy, allow_failed=allow_failed)
                bt, _ = _board_test_of(copy, reader, model, cm, defaults.ZONE_MM)
            except EndomeasureError:
                return None
    if cm.misfit is None:
        return None
    out = {
        "misfit_px": float(np.sqrt(np.mean(cm.misfit.std**2))),
        "noise_px": cm.misfit.noise_sigma,
        **cm.misfit.to_dict(),
    }
    for key, with_model in (("with", True), ("without", False)):
        noise = NoiseAssumptions(model_error=with_model)
        image = board_test_noise(bt, cm.model, noise, cm, model)
        pred = board_predictions(bt, cm.model, image, **noise.propagation(cm))
        zones = [z for z in prediction_zones(bt, pred, defaults.ZONE_MM) if z["n"] >= MIN_ZONE_N]
        ratios = [z["actual_std"] / z["predicted_std"] for z in zones]
        out[key] = {
            "band": within_band(bt, pred.bias, pred.std),
            "close": int(sum(abs(r - 1.0) <= STD_RATIO_LIMIT for r in ratios)),
            "zones": len(zones),
            "ratio_median": float(np.median(ratios)) if ratios else float("nan"),
        }
    return out


def _cells(r: dict) -> str:
    return " | ".join(
        f"{100 * r[k]['band']:.1f} % | {r[k]['close']} of {r[k]['zones']} | "
        f"{r[k]['ratio_median']:.2f}"
        for k in ("without", "with")
    )


def section(rows: dict, designs: str, extra: dict) -> str:
    significant = {s: r for s, r in rows.items() if r["misfit_px"] >= SIGNIFICANT * r["noise_px"]}

    def totals(group: dict, key: str) -> str:
        if not group:
            return "-"
        close = sum(r[key]["close"] for r in group.values())
        zones = sum(r[key]["zones"] for r in group.values())
        band = np.mean([r[key]["band"] for r in group.values()])
        share = f"{100 * close / zones:.1f} %" if zones else "-"
        return f"{100 * band:.1f} % | {close} of {zones} ({share})"

    lines = [
        f"Designs {designs} with a usable raytrace calibration ({len(rows)}), made by "
        "`python bench/misfit_designs.py WORK --default SESSION` on an `accuracy_designs.py` "
        f"work folder. A misfit is *significant* from {SIGNIFICANT:g} of the noise (RMS over "
        "halves and coordinates) on.",
        "",
        "| designs | band without the term (mean) | zones within +-25 % without | band with "
        "(mean) | zones within +-25 % with |",
        "|---|---:|---:|---:|---:|",
        f"| all ({len(rows)}) | {totals(rows, 'without')} | {totals(rows, 'with')} |",
        f"| significant misfit ({len(significant)}) | {totals(significant, 'without')} | "
        f"{totals(significant, 'with')} |",
        "",
        "Per design with a significant misfit, and the default preset: misfit / noise (px, RMS "
        "over halves and coordinates), the misfit's correlation between the halves (u, v) and "
        "kernel per coordinate (ring / decay, px, and stretch across it); then without and with "
        "the term: errors inside the "
        "2-sigma band, zones within +-25 %, median actual / predicted std.",
        "",
        "| case | misfit / noise px | rho halves u, v | kernel px | band without | zones | "
        "ratio | band with | zones | ratio |",
        "|---|---:|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    cases = {f"design {s}": r for s, r in sorted(significant.items())} | extra
    for name, r in cases.items():
        rho = ", ".join(f"{v:+.2f}" for v in r["misfit_rho_halves"])
        ring, decay = (np.broadcast_to(v, (2,)) for v in r["misfit_kernel_px"])
        stretch = np.broadcast_to(r.get("misfit_kernel_stretch", 1.0), (2,))
        kernel = ", ".join(f"{c} {ring[k]:.0f} / {decay[k]:.0f} x{stretch[k]:.2g}"
                           for k, c in enumerate("uv"))  # fmt: skip
        lines.append(
            f"| {name} | {r['misfit_px']:.4f} / {r['noise_px']:.4f} | {rho} | {kernel} | "
            f"{_cells(r)} |"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = work_parser(__doc__)
    parser.add_argument("--default", type=Path, help="a calibrated session of the default preset")
    args = parser.parse_args(argv)
    report = Report("bench/misfit_designs.py", args, ACCURACY)
    store = args.work / "misfit_designs.jsonl"
    done = stored_designs(store, args.fresh)
    finished = _finished(args.work)
    rows = {}
    for seed in parse_seeds(args.designs):
        if seed in done:
            if "with" in done[seed]:
                rows[seed] = done[seed]
            continue
        if seed not in finished:
            continue
        r = misfit_figures(args.work / f"design_{seed:03d}.h5")
        record = {"seed": seed, **(r or {})}
        store_design(store, record)
        if r is not None:
            rows[seed] = record
            print(seed, r["misfit_px"], r["without"], r["with"], flush=True)
    extra = {}
    if args.default is not None:
        for model, allow in (("raytrace", False), ("pinhole", True)):
            r = misfit_figures(args.default, model, allow_failed=allow)
            if r is not None:
                label = "default preset, pinhole (verdict failed)" if allow else "default preset"
                extra[label] = r
                print(label, r["misfit_px"], r["without"], r["with"], flush=True)
    return report.finish({SECTION: section(rows, args.designs, extra)})


if __name__ == "__main__":
    raise SystemExit(main())
