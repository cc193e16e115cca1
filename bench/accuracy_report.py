"""Measure and predict-error accuracy on a rendered set -> docs/accuracy.md.

    python bench/accuracy_report.py [DATA] [--work DIR]

DATA is a folder written by `endomeasure simulate` (default: sample_sessions/). The
script runs the commands a user would: `endomeasure detect` for each board spec of the
calib and test sets (the spec from the ground truth), `endomeasure calibrate --model
all`, `endomeasure measure --board-test --model all`, then `predict-error --board-test`
at the measured detection noise for several correlations. Besides the commands it uses
the simulator's truth (true corner pixels) for two figures a user could not have: the
detection noise and its correlations, and the board test on the *true* pixels (the model
error alone, without image noise). Tables go to the "measure" section of
docs/accuracy.md (between its markers).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from _common import replace_section  # noqa: E402

EM = [sys.executable, "-m", "endomeasure"]
ACC = ROOT / "docs" / "accuracy.md"
RHOS = (0.0, 0.3, 0.6, 0.9)


def run(*args) -> dict | None:
    out = subprocess.run([*EM, *map(str, args)], capture_output=True, text=True)
    if out.returncode not in (0, 1):
        sys.exit(f"failed: {' '.join(map(str, args))}\n{out.stderr}")
    return json.loads(out.stdout) if "--json" in args else None


def build_session(data: Path, session: Path) -> dict:
    sim = json.loads((data / "simulation.json").read_text())
    session.unlink(missing_ok=True)
    for set_name in ("calib", "test"):
        groups: dict[str, list[str]] = {}
        for im in sim["sets"][set_name]["images"]:
            groups.setdefault(im["board_spec"], []).append(str(data / im["image"]))
        for spec, files in groups.items():
            run(
                "detect",
                session,
                *files,
                "--board",
                spec,
                "--set",
                set_name,
                "--workers",
                2,
                "--json",
            )
    return run("calibrate", session, "--model", "all", "--json")


def truth_of(data: Path, image: str) -> dict:
    return json.loads((data / "test" / f"{image}.json").read_text())


def detection_noise(session: Path, data: Path) -> dict:
    """Detected minus true corner pixels of the test set: sigma and correlations."""
    from endomeasure.conventions import Half
    from endomeasure.io.session import open_session

    with open_session(session) as s:
        test = s.image_names("test")
        dets = [d for d in s.detections() if d.image in test and d.ok]
    el, er, pairs = [], [], []
    for image in test:
        ds = {Half.parse(d.half).label: d for d in dets if d.image == image}
        if len(ds) < 2:
            continue
        t = truth_of(data, image)
        tid = {int(i): k for k, i in enumerate(t["corners"]["ids"])}
        cols = int(t["board_spec"].split(":")[1].split("x")[0])
        ids = np.intersect1d(ds["left"].ids, ds["right"].ids)
        e = {}
        for h in ("left", "right"):
            d = ds[h]
            row = {int(i): k for k, i in enumerate(d.ids)}
            tp = np.array(t["corners"]["pixels"][h])
            e[h] = np.array([d.pixels[row[i]] - tp[tid[i]] for i in ids])
        el.append(e["left"])
        er.append(e["right"])
        at = {int(i): k for k, i in enumerate(ids)}
        for i, k in at.items():
            for j in ((i + 1) if (i % cols) + 1 < cols else -1, i + cols):
                if j in at:
                    for h in ("left", "right"):
                        pairs.append((e[h][k], e[h][at[j]]))
    el, er = np.concatenate(el), np.concatenate(er)
    pairs = np.array(pairs)
    both = np.concatenate([el, er])
    return {
        "n": int(el.shape[0]),
        "sigma": float(np.sqrt(np.mean((both - both.mean(axis=0)) ** 2))),
        "rho_images": [float(np.corrcoef(el[:, k], er[:, k])[0, 1]) for k in range(2)],
        "rho_points": [float(np.corrcoef(pairs[:, 0, k], pairs[:, 1, k])[0, 1]) for k in range(2)],
    }


def truth_board_test(session: Path, data: Path, zone_mm: float) -> dict:
    """The board test on the true corner pixels: the models' own error, no image noise."""
    from endomeasure.io.session import open_session
    from endomeasure.pipeline.measure import BoardSet, load_calibrated_model, run_board_test

    with open_session(session) as s:
        models = {n: load_calibrated_model(s, n, session).model for n in s.model_names()}
        test = s.image_names("test")
    sets: dict[str, BoardSet] = {}
    for image in test:
        t = truth_of(data, image)
        tg = t["target"]
        bs = sets.setdefault(
            t["board_spec"],
            BoardSet(t["board_spec"], tg["cols"], tg["rows"], tg["square_mm"], [], [], [], []),
        )
        px = t["corners"]["pixels"]
        bs.images.append(image)
        bs.ids.append(np.asarray(t["corners"]["ids"], dtype=np.int64))
        bs.left.append(np.asarray(px["left"], dtype=float))
        bs.right.append(np.asarray(px["right"], dtype=float))
    return {n: run_board_test(n, m, list(sets.values()), zone_mm) for n, m in models.items()}


def fmt(v, digits=4, sign=True):
    return "-" if v is None else (f"{v:+.{digits}f}" if sign else f"{v:.{digits}f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", nargs="?", default=str(ROOT / "sample_sessions"))
    ap.add_argument("--work", default=None, help="folder for the session (default: a temp dir)")
    ap.add_argument("--zone-mm", type=float, default=5.0)
    args = ap.parse_args()
    data = Path(args.data).resolve()
    work = Path(args.work or tempfile.mkdtemp(prefix="endomeasure-acc-"))
    work.mkdir(parents=True, exist_ok=True)
    session = work / "accuracy.h5"
    cal = build_session(data, session)
    bt = run(
        "measure",
        session,
        "--board-test",
        "--model",
        "all",
        "--zone-mm",
        args.zone_mm,
        "--json",
        "--plot",
        work / "fig4.png",
    )
    noise = detection_noise(session, data)
    truth = truth_board_test(session, data, args.zone_mm)
    sigma = noise["sigma"]
    preds = {}
    for key, extra in (
        ("iid", []),
        ("iid, image noise only", ["--no-calibration"]),
        *((f"rho_images {r:g}", ["--rho-images", r]) for r in RHOS[1:]),
        *((f"rho_points {r:g}", ["--rho-points", r]) for r in RHOS[1:]),
    ):
        preds[key] = run(
            "predict-error",
            session,
            "--board-test",
            "--model",
            "raytrace",
            "--sigma",
            sigma,
            "--zone-mm",
            args.zone_mm,
            *extra,
            "--json",
            *(["--plot", work / "fig5.png"] if key == "iid" else []),
        )

    sim = json.loads((data / "simulation.json").read_text())
    n_test = len(sim["sets"]["test"]["images"])
    lines = [
        "## Measurement (board test) and error prediction",
        "",
        f"Reproduce: `python bench/accuracy_report.py {data.name if data.parent == ROOT else data}`"
        " (builds a session with `endomeasure detect` / `calibrate`, then runs `endomeasure "
        "measure --board-test --model all` and `endomeasure predict-error --board-test` at the "
        "measured detection noise; about a minute). Data: preset "
        f"`{sim['preset']['name']}`, seed {sim['seed']}, {n_test} test images "
        "(board perpendicular to the axis, 1 mm steps). Zones of "
        f"{args.zone_mm:g} mm along z; error = measured - true; relative = mean / true value.",
        "",
        "Calibration: "
        + ", ".join(
            f"{k} RMS {m['rms_px']:.3f} px ({m['n_corners']} corners, {m['n_outliers']} outliers)"
            for k, m in cal["models"].items()
        )
        + ".",
        "",
        f"Detection noise of the test set against the simulator's true corners ({noise['n']} "
        f"corners in both halves): sigma {sigma:.4f} px per coordinate; correlation of a "
        f"corner's left and right errors rho_images u {noise['rho_images'][0]:+.2f}, v "
        f"{noise['rho_images'][1]:+.2f}; between neighbouring corners of one half rho_points u "
        f"{noise['rho_points'][0]:+.2f}, v {noise['rho_points'][1]:+.2f}.",
        "",
        "### Board test: mean error (std) per zone, detected corners",
        "",
        "| model | board | kind | zone mm | n | mean | std | mean % of true | mean / std |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in bt["summary"]:
        rel = r["relative_mean_percent"]
        ratio = r["mean_error"] / r["std_error"] if r["std_error"] else None
        lines.append(
            f"| {r['model']} | {r['board'].removeprefix('chessboard:')} | {r['kind']} | "
            f"{r['zone_start']:g}-{r['zone_end']:g} | {r['n']} | {fmt(r['mean_error'])} | "
            f"{fmt(r['std_error'], sign=False)} | {fmt(rel, 2)} | {fmt(ratio, 2)} |"
        )
    lines += [
        "",
        "### Board test on the true corner pixels (model error alone)",
        "",
        "| model | board | kind | zone mm | mean | std | mean % of true |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, mb in truth.items():
        s = mb.summary
        for i in range(s.kind.shape[0]):
            rel = 100 * s.mean_error[i] / s.true[i] if s.true[i] else None
            lines.append(
                f"| {name} | {mb.summary_board[i].removeprefix('chessboard:')} | {s.kind[i]} | "
                f"{s.zone_start[i]:g}-{s.zone_end[i]:g} | {fmt(float(s.mean_error[i]), 5)} | "
                f"{fmt(float(s.std_error[i]), 5, False)} | {fmt(rel, 3)} |"
            )
    p = preds["iid"]
    lines += [
        "",
        f"### Predicted vs actual (raytrace, UT, sigma {sigma:.4f} px, rho 0, with the "
        "calibration covariance)",
        "",
        f"Errors inside their predicted 2-sigma band: {100 * p['within_band']:.1f} % "
        f"(image noise only: {100 * preds['iid, image noise only']['within_band']:.1f} %). "
        "Predictions are made at the pixels of the ideal board at its estimated pose.",
        "",
        "| board | kind | zone mm | n | actual mean | predicted mean | actual std | "
        "predicted std | actual / predicted std | in 2-sigma band |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for z in p["zones"]:
        lines.append(
            f"| {z['board'].removeprefix('chessboard:')} | {z['kind']} | "
            f"{z['zone_start']:g}-{z['zone_end']:g} | {z['n']} | {fmt(z['actual_mean'])} | "
            f"{fmt(z['predicted_mean'])} | {fmt(z['actual_std'], sign=False)} | "
            f"{fmt(z['predicted_std'], sign=False)} | {fmt(z['std_ratio'], 2, False)} | "
            f"{100 * z['within_band']:.0f} % |"
        )
    lines += [
        "",
        "### Effect of correlated image errors on the prediction (raytrace)",
        "",
        "Mean over zones of the predicted std relative to rho = 0, and the median ratio "
        "actual / predicted std:",
        "",
        "| assumption | x-segment | y-segment | point-plane | area | median actual/predicted |"
        " in 2-sigma band |",
        "|---|---|---|---|---|---|---|",
    ]
    base = {
        k: np.mean([z["predicted_std"] for z in p["zones"] if z["kind"] == k])
        for k in ("x-segment", "y-segment", "point-plane", "area")
    }
    for key, q in preds.items():
        rel = [
            np.mean([z["predicted_std"] for z in q["zones"] if z["kind"] == k]) / base[k]
            for k in base
        ]
        med = np.median([z["std_ratio"] for z in q["zones"] if z["std_ratio"] is not None])
        lines.append(
            f"| {key} | "
            + " | ".join(f"{v:.2f}" for v in rel)
            + f" | {med:.2f} | {100 * q['within_band']:.1f} % |"
        )
    body = "\n".join(lines)
    ACC.write_text(replace_section(ACC.read_text(), "measure", body))
    print(body)
    print(f"\nsession, fig4.png and fig5.png in {work}", file=sys.stderr)


if __name__ == "__main__":
    main()
