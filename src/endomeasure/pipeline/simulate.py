"""``endomeasure simulate``: render image sets with exact ground truth (the digital twin).

Output layout (documented in ``docs/simulator.md``)::

    OUT_DIR/simulation.json          manifest: preset, truth optics, seed, image list
    OUT_DIR/preset.json              the preset rendered (with --preset random: the drawn design)
    OUT_DIR/calib/calib_000.png      8-bit grey image, both halves side by side
    OUT_DIR/calib/calib_000.json     its ground truth
    OUT_DIR/test/...  OUT_DIR/scene/...  OUT_DIR/charuco/...

Deterministic for a seed: poses come from a generator per set, sensor noise from a
generator per image, both derived from the seed.
"""

from __future__ import annotations

import json
import os
import time
import zlib
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from endomeasure import __version__
from endomeasure.errors import BadInputError
from endomeasure.simulate.manifest import MANIFEST_NAME

__all__ = ["SimulationReport", "simulate", "checked_sets", "MANIFEST_NAME", "MANIFEST_FORMAT"]

MANIFEST_FORMAT = "endomeasure-simulation"
MANIFEST_VERSION = 1
PRESET_FILE = "preset.json"
RANDOM_PRESET = "random"
_PNG_COMPRESSION = 9  # smallest files; PNG is lossless, so this changes nothing but size


@dataclass(frozen=True)
class SimulationReport:
    """What :func:`simulate` wrote.

    Attributes
    ----------
    out_dir : str
    preset : str
    seed : int
    noise_free : bool
    design_seed : int or None
        The design seed of a ``random`` preset (None for a named or file preset).
    split : int
        First column of the right half in the rendered images.
    sets : dict
        Per set: ``images`` (count), ``fully_visible`` (boards whole in both halves),
        ``files`` (relative paths of the images).
    seconds : float
        Wall time, s.
    """

    out_dir: str
    preset: str
    seed: int
    noise_free: bool
    design_seed: int | None
    split: int
    sets: dict[str, dict[str, Any]] = field(default_factory=dict)
    seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def checked_sets(names: Iterable[str]) -> list[str]:
    """Image set names, validated, in canonical order."""
    from endomeasure.simulate.scenes import SET_NAMES

    names = [names] if isinstance(names, str) else list(names)
    unknown = sorted(set(names) - set(SET_NAMES))
    if unknown or not names:
        raise BadInputError(
            f"unknown image set(s) {', '.join(unknown) or '(none given)'}",
            hint=f"use a comma-separated list of {', '.join(SET_NAMES)}",
        )
    return [s for s in SET_NAMES if s in names]


def _load(preset, design_seed: int | None):
    """The preset to render: a named or file preset, or the random design of a seed."""
    from endomeasure.simulate.preset import Preset, load_preset

    if str(preset) != RANDOM_PRESET:
        if design_seed is not None:
            raise BadInputError(
                "--design-seed only applies to --preset random", hint="drop one of the two"
            )
        return load_preset(preset)
    if design_seed is None or int(design_seed) < 0:
        raise BadInputError(
            "--preset random needs a non-negative --design-seed",
            hint="e.g. endomeasure simulate OUT --preset random --design-seed 1",
        )
    from endomeasure.simulate.design import draw_design

    try:
        data = draw_design(int(design_seed))
    except ValueError as exc:
        raise BadInputError(f"cannot draw design {design_seed}: {exc}") from None
    return Preset.from_dict(data, source=f"random:design-seed={int(design_seed)}")


def _noise_rng(seed: int, set_name: str, index: int):
    import numpy as np

    return np.random.default_rng([int(seed), zlib.crc32(set_name.encode()), int(index), 0x6E6F6973])


def _remove_stale(folder: Path, set_name: str) -> None:
    """Delete earlier renders of a set, so a smaller run leaves no foreign images behind."""
    for path in folder.glob(f"{set_name}_*"):
        if (path.suffix in (".png", ".json") or path.name.endswith(".depth.npy")) and (
            path.is_file()
        ):
            path.unlink()


def _render_shot(loaded, set_name: str, shot, folder: Path, seed: int, noise_free: bool):
    """Render one image with its truth file; its manifest entry."""
    import cv2
    import numpy as np

    from endomeasure.simulate.render import render
    from endomeasure.simulate.truth import DEPTH_SUFFIX, image_truth, true_depth

    rng = None if noise_free else _noise_rng(seed, set_name, shot.index)
    result = render(loaded, shot.target, rng=rng, noise_free=noise_free)
    png = folder / f"{shot.name}.png"
    if not cv2.imwrite(str(png), result.image, [cv2.IMWRITE_PNG_COMPRESSION, _PNG_COMPRESSION]):
        raise OSError(f"could not write {png}")
    info = {
        "noise_free": bool(noise_free),
        "seed": int(seed),
        "exposure": result.exposure,
        "supersampling": f"{loaded.supersampling}x{loaded.supersampling}",
    }
    truth = image_truth(loaded, shot, png.name, info)
    depth_file = None
    if set_name == "scene":
        depth_file = f"{shot.name}{DEPTH_SUFFIX}"
        np.save(folder / depth_file, true_depth(loaded, shot.target), allow_pickle=False)
        truth["depth_map"] = {
            "file": depth_file,
            "dtype": "float32",
            "unit": "mm",
            "meaning": "z in the camera frame of the first target point on each pixel "
            "centre's ray through the truth optics; NaN: background or a failed ray",
        }
    (folder / f"{shot.name}.json").write_text(json.dumps(truth, indent=1) + "\n")
    entry = {"image": f"{set_name}/{png.name}", "truth": f"{set_name}/{shot.name}.json"}
    if depth_file is not None:
        entry["depth"] = f"{set_name}/{depth_file}"
    if "board_spec" in truth:
        entry["board_spec"] = truth["board_spec"]
        entry["distance_mm"] = round(truth["distance_mm"], 4)
        entry["board_fully_visible"] = all(truth["board_fully_visible"].values())
    return entry


def _kept_sets(manifest_path: Path, rendered: dict, loaded, seed: int, noise_free: bool) -> dict:
    """The sets of an earlier run in the folder that this run did not render, when they
    were made by the same preset data (as far as those sets depend on it), seed and noise."""
    from endomeasure.simulate.preset import data_digest, restrict_to_sets

    if not manifest_path.is_file():
        return {}
    try:
        old = json.loads(manifest_path.read_text())
        kept = {k: v for k, v in old.get("sets", {}).items() if k not in rendered}
        same_run = (
            old.get("seed") == seed
            and old.get("noise_free") == bool(noise_free)
            and data_digest(restrict_to_sets(old.get("preset_data", {}), kept))
            == data_digest(loaded.for_sets(kept))
        )
    except (ValueError, AttributeError, TypeError):
        return {}
    return kept if same_run else {}


def _truth_entries(loaded) -> dict[str, Any]:
    """The manifest's truth-optics fields: what the simulator traced, and the nearest
    ``raytrace`` model (exact only when the design is representable in that family)."""
    exact = loaded.raytrace_representable
    return {
        "truth_optics": {
            "code": "endomeasure.simulate.truth_optics",
            "note": "the simulator's own tracer; truth_model is a raytrace document, not it",
            "raytrace_representable": bool(exact),
        },
        "truth_model": loaded.truth_model.to_dict(),
        "truth_model_kind": "exact" if exact else "approximate-seed",
    }


def _write_manifest(manifest_path: Path, loaded, manifest_sets: dict, seed, noise_free) -> None:
    from endomeasure.simulate.preset import data_digest

    # the preset as far as the folder's sets depend on it: adding a set to a preset
    # leaves the manifests of its other sets unchanged
    recorded = loaded.for_sets(manifest_sets)
    manifest = {
        "format": MANIFEST_FORMAT,
        "version": MANIFEST_VERSION,
        "created_by": f"endomeasure {__version__}",
        "seed": int(seed),
        "noise_free": bool(noise_free),
        "preset": {"name": loaded.name, "source": loaded.source, "sha256": data_digest(recorded)},
        "image_size": list(loaded.image_size),
        "split": loaded.split,
        **_truth_entries(loaded),
        **({"design": loaded.data["design"]} if "design" in loaded.data else {}),
        "sets": {k: manifest_sets[k] for k in sorted(manifest_sets)},
        "preset_data": recorded,
    }
    tmp = manifest_path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(manifest, indent=1) + "\n")
    tmp.replace(manifest_path)


def simulate(
    out_dir: str | os.PathLike,
    preset: str | os.PathLike = "default",
    sets: Iterable[str] = ("calib", "test", "scene"),
    seed: int = 0,
    noise_free: bool = False,
    design_seed: int | None = None,
    on_progress: Callable[[int, int, str], None] | None = None,
) -> SimulationReport:
    """Render the requested image sets of a preset with their ground truth.

    Parameters
    ----------
    out_dir : path-like
        Created if missing; earlier renders of the same sets in it are replaced.
    preset : str or path-like
        A built-in preset name, a preset JSON file, or ``random``: the probe
        :func:`~endomeasure.simulate.design.draw_design` draws for ``design_seed``.
    sets : iterable of str
        Any of ``calib``, ``test``, ``scene``, ``charuco`` (the ChArUco set is not
        rendered by default); a single name is one set.
    seed : int
        Non-negative; the same seed gives the same images, byte for byte.
    noise_free : bool
        Render without shot and read noise (still 8-bit).
    design_seed : int, optional
        Non-negative; required with ``preset='random'`` and only allowed with it.
    on_progress : callable(done, total, name), optional
        Called after each image is written.

    Returns
    -------
    SimulationReport

    Raises
    ------
    BadInputError
        Unknown preset or set, negative seed, a design seed without ``random`` (or the
        reverse), or an output folder that cannot be written.
    """
    from endomeasure.simulate.scenes import plan_set

    start = time.perf_counter()
    if int(seed) < 0:
        raise BadInputError(f"seed must be a non-negative integer, not {seed}")
    set_names = checked_sets(sets)
    loaded = _load(preset, design_seed)
    from endomeasure.io.outputs import checked_output_dir

    out = checked_output_dir(out_dir, "output folder", create_parents=True)
    try:
        plans = {name: plan_set(loaded, name, int(seed)) for name in set_names}
    except ValueError as exc:
        raise BadInputError(
            f"cannot plan the image sets of preset {loaded.name!r}: {exc}", path=loaded.source
        ) from None
    total = sum(len(p) for p in plans.values())
    done = 0
    manifest_sets: dict[str, Any] = {}
    report_sets: dict[str, dict[str, Any]] = {}
    try:
        out.mkdir(parents=True, exist_ok=True)
        for name, shots in plans.items():
            folder = out / name
            folder.mkdir(exist_ok=True)
            _remove_stale(folder, name)
            entries = []
            for shot in shots:
                entries.append(_render_shot(loaded, name, shot, folder, seed, noise_free))
                done += 1
                if on_progress is not None:
                    on_progress(done, total, shot.name)
            manifest_sets[name] = {"protocol": loaded.sets[name], "images": entries}
            fully = sum(bool(e.get("board_fully_visible", False)) for e in entries)
            report_sets[name] = {
                "images": len(entries),
                "fully_visible": fully if name != "scene" else None,
                "files": [e["image"] for e in entries],
            }
        (out / PRESET_FILE).write_text(json.dumps(loaded.data, indent=1) + "\n")
        manifest_path = out / MANIFEST_NAME
        manifest_sets.update(_kept_sets(manifest_path, manifest_sets, loaded, seed, noise_free))
        _write_manifest(manifest_path, loaded, manifest_sets, seed, noise_free)
    except OSError as exc:
        raise BadInputError(
            f"cannot write the simulated images ({exc.strerror or exc})",
            path=str(out),
            hint="choose a writable output folder",
        ) from None
    return SimulationReport(
        out_dir=str(out),
        preset=loaded.name,
        seed=int(seed),
        noise_free=bool(noise_free),
        design_seed=None if design_seed is None else int(design_seed),
        split=loaded.split,
        sets=report_sets,
        seconds=time.perf_counter() - start,
    )
