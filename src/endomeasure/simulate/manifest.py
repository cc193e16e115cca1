"""Reading a simulated image set back: its manifest and ground truth (plain JSON).

``endomeasure simulate OUT_DIR`` writes ``OUT_DIR/simulation.json`` (the manifest) and a
ground-truth JSON next to every image (``docs/simulator.md``). Demos, accuracy reports
and tests read them through these functions instead of parsing the files themselves.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = ["MANIFEST_NAME", "load_manifest", "board_groups", "load_truth", "load_true_depth"]

MANIFEST_NAME = "simulation.json"


def load_manifest(root: str | Path) -> dict[str, Any]:
    """The manifest of a simulated set in folder ``root``."""
    return json.loads((Path(root) / MANIFEST_NAME).read_text())


def board_groups(root: str | Path, set_name: str) -> list[tuple[str, list[Path]]]:
    """The images of one set grouped by board spec, in a stable order.

    Returns
    -------
    list of (board spec, image paths)
        One ``endomeasure detect ... --board SPEC --set SET_NAME`` call per entry covers
        the set (a calibration set shows three boards).
    """
    root = Path(root)
    groups: dict[str, list[Path]] = {}
    for item in load_manifest(root)["sets"].get(set_name, {}).get("images", []):
        if item.get("board_spec"):
            groups.setdefault(item["board_spec"], []).append(root / item["image"])
    return sorted(groups.items())


def load_truth(root: str | Path, image_name: str) -> dict[str, Any]:
    """Ground truth of an image by its stem (``calib_005``), from the manifest's list."""
    root = Path(root)
    for entry in load_manifest(root)["sets"].values():
        for item in entry.get("images", []):
            if Path(item["image"]).stem == image_name:
                return json.loads((root / item["truth"]).read_text())
    raise KeyError(f"no image {image_name!r} in the simulated set at {root}")


def load_true_depth(root: str | Path, image_name: str):
    """True depth map of a scene image by its stem, ndarray (H, W) float32 mm, NaN where
    no target surface is seen (``docs/simulator.md``, "Ground truth JSON").

    Raises
    ------
    KeyError
        No such image, or it has no depth map (board images, or rendered before it).
    """
    import numpy as np

    root = Path(root)
    for entry in load_manifest(root)["sets"].values():
        for item in entry.get("images", []):
            if Path(item["image"]).stem == image_name:
                if "depth" not in item:
                    raise KeyError(f"image {image_name!r} has no true depth map in {root}")
                return np.load(root / item["depth"], allow_pickle=False)
    raise KeyError(f"no image {image_name!r} in the simulated set at {root}")
