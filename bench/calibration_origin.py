"""Where the raytrace calibration puts the model frame's origin along the axis.

    PYTHONPATH=src .venv/bin/python bench/calibration_origin.py --designs out/designs \
        [--design-seeds 1-12] [--session out/demo/demo.h5]

For each random design calibrated by ``bench/accuracy_designs.py`` (its session
``design_NNN.h5``, its truth in ``design_NNN/preset.json``; with ``--session``, the
default preset's demo calibration too):

- the model's z error of true points at the nearest and the farthest depth its boards
  were seen at, with the sigma of that z from the fit's own covariance and from the
  covariance measurements use, which also varies the absorbed extensions the fit held
  (``docs/models.md``, "Uncertainty of what the fit held"; :func:`_common.calibration_dz`);
- two prism distances along the axis, model minus truth: the apex (the front faces'
  common edge, at its point nearest the axis) and the apparent pupil distance (the air
  gap to the rear face plus the glass thickness over the index), which board images fix.

An apex offset equal to the z error, with the apparent distance right, is the origin set
off by the split between air gap and glass, which the residuals do not see.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "src"))

from _common import (  # noqa: E402
    ACCURACY,
    Report,
    calibration_dz,
    command_line,
    parse_seeds,
    script_parser,
)


def _on_axis(faces, n_glass: float) -> tuple[float, float]:
    """The apex's z (the point of the front faces' common edge nearest the axis) and the
    pupil's apparent distance seen from it through the glass, ``z_rear + (z_apex -
    z_rear) / n`` (the air gap, plus the glass as thick as it looks), of three faces
    ``(normal, d)`` (rear, left, right), mm."""
    (rear_n, rear_d), (left_n, left_d), (right_n, right_d) = faces
    # least x^2 + y^2 on the edge {left . p = left_d, right . p = right_d} (Lagrange)
    kkt = np.zeros((5, 5))
    kkt[0, 0] = kkt[1, 1] = 2.0
    kkt[:3, 3:] = np.stack([left_n, right_n], axis=1)
    kkt[3:, :3] = np.stack([left_n, right_n])
    apex = np.linalg.lstsq(kkt, np.array([0.0, 0.0, 0.0, left_d, right_d]), rcond=None)[0][2]
    rear = rear_d / rear_n[2]
    return float(apex), float(rear + (apex - rear) / n_glass)


def row(label: str, session: Path, truth) -> str:
    """One calibration's figures against its truth optics."""
    from endomeasure.io.records import model_from_record, stored_model_record
    from endomeasure.io.session import open_session
    from endomeasure.pipeline import calibrated_model

    with open_session(session) as reader:
        cm = calibrated_model(reader, "raytrace", session)
        record = stored_model_record(reader, "raytrace", session)
    fitted = model_from_record(record)
    names = [str(n) for n in record.arrays["free_names"]]
    order = [names.index(fitted.PARAM_NAMES[i]) for i in np.flatnonzero(fitted.free_mask)]
    own = np.asarray(record.arrays["covariance"], dtype=np.float64)[np.ix_(order, order)]
    err_near, err_far, own_near, own_far = calibration_dz(fitted, own, cm.depth_range_mm, truth)
    _, _, sig_near, sig_far = calibration_dz(cm.model, cm.param_cov, cm.depth_range_mm, truth)
    model = cm.model
    faces = [model.face(f) for f in ("rear", "left", "right")]
    apex, apparent = _on_axis(faces, float(model.n_glass))
    true_faces = [(p.normal, p.d) for p in (truth.rear, truth.left, truth.right)]
    true_apex, true_apparent = _on_axis(true_faces, float(truth.n_glass))
    held = ", ".join(str(n) for n in np.asarray(record.attrs.get("uncertain", []), dtype=object))
    near, far = cm.depth_range_mm
    return (
        f"| {label} | {near:.1f} / {far:.1f} | {err_near:+.3f} / {err_far:+.3f} | "
        f"{own_near:.3f} / {own_far:.3f} | {sig_near:.3f} / {sig_far:.3f} | {held or '-'} | "
        f"{apex - true_apex:+.3f} | {1000 * (apparent - true_apparent):+.1f} |"
    )


def main() -> int:
    parser = script_parser(__doc__)
    parser.add_argument("--designs", type=Path, required=True, help="random designs' WORK folder")
    parser.add_argument("--design-seeds", default="1-12", help="e.g. 1-12 or 1,5")
    parser.add_argument("--session", type=Path, default=None, help="the default preset's demo")
    args = parser.parse_args()
    from endomeasure.simulate.preset import load_preset

    rows = []
    if args.session is not None:
        rows.append(row("default preset", args.session, load_preset("default").truth_optics))
    for seed in parse_seeds(args.design_seeds):
        session = args.designs / f"design_{seed:03d}.h5"
        preset = args.designs / f"design_{seed:03d}" / "preset.json"
        if session.exists() and preset.exists():
            rows.append(row(f"design {seed}", session, load_preset(preset).truth_optics))
    command = command_line(
        "calibration_origin.py",
        ("--designs", args.designs),
        ("--design-seeds", args.design_seeds),
        ("--session", args.session),
    )
    body = "\n".join([
        "## The calibration's frame origin along the axis",
        "",
        f"`{command}`: the raytrace calibration of each random design (and the default "
        "preset's demo) against its truth optics. z error: true points at the nearest / "
        "farthest depth the boards were seen at, triangulated from their true pixels "
        "(median over the field). Their sigma: from the fit's own covariance, and from "
        "the covariance measurements use, which also varies the held absorbed "
        "extensions (docs/models.md, \"Uncertainty of what the fit held\"). Apex and "
        "apparent pupil distance: model minus truth along the axis (docs/surface.md).",
        "",
        "| calibration | board depths, mm | z error, mm | fit's sigma of z, mm | "
        "measurements' sigma of z, mm | held, not ruled out | apex offset, mm | "
        "apparent pupil distance offset, um |",
        "|---|---|---|---|---|---|---:|---:|",
        *rows,
    ])  # fmt: skip
    return Report("bench/calibration_origin.py", args, ACCURACY).finish(
        {"calibration-origin": body}
    )


if __name__ == "__main__":
    sys.exit(main())
