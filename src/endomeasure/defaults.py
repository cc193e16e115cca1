"""The defaults of the commands' options, written once: the CLI shows them, the pipeline
and the core apply them. Standard library only, so that ``endomeasure --help`` stays fast.
"""

__all__ = ["ALL_MODELS", "WARN_PERCENT", "PATCH_PX", "ZONE_MM"]

WARN_PERCENT = 5.0
"""Accuracy-index threshold (percent): the +-5 % that commercial videoscopes quote for
stereo measurements in their working range."""

PATCH_PX = 15
"""Side of the correlation patch of the automatic search in the other half (px, odd)."""

ZONE_MM = 5.0
"""Width of the distance zones of the board test (mm): the paper's Fig. 4 uses zones of
a few mm, wide enough for several images per zone and a per-zone standard deviation."""

ALL_MODELS = "all"
"""The ``--model`` value that asks for every registered model."""
