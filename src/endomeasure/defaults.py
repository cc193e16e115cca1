"""The defaults of the commands' options, written once: the CLI shows them, the pipeline
and the core apply them; and the limits on inputs and options that the commands check
before any work, each with the reason for its value (the refusal's message gives it).
Standard library only, so that ``endomeasure --help`` stays fast.
"""

__all__ = [
    "ALL_MODELS",
    "LOCK_WAIT_S",
    "MAX_IMAGE_PIXELS",
    "MAX_IMAGE_SIDE",
    "MAX_MAP_DEPTHS",
    "MAX_MAP_POINTS",
    "MAX_MC_SAMPLES",
    "MAX_PATCH_PX",
    "MAX_POINTS_PER_MEASUREMENT",
    "MAX_SIGMA_PX",
    "MAX_STORED_ELEMENTS",
    "MAX_WORKERS_PER_CPU",
    "MIN_ZONE_MM",
    "PATCH_PX",
    "DENSE_WINDOW_PX",
    "DENSE_WINDOW_RANGE_PX",
    "PROFILE_WINDOW_RANGE_PX",
    "TRUST_BANDS_PERCENT",
    "WARN_PERCENT",
    "ZONE_MM",
]

LOCK_WAIT_S = 120.0
"""How long a command waits for another command's lock on a session (s; ``--wait``):
edits hold it only while they write, so two minutes means a stuck peer."""

WARN_PERCENT = 5.0
"""Accuracy-index threshold (percent): the +-5 % that commercial videoscopes quote for
stereo measurements in their working range."""

TRUST_BANDS_PERCENT = (1.0, WARN_PERCENT)
"""Limits of the report's trust map (percent of a 1 mm length, the 95 % error bound):
green within 1 %, the accuracy stereo endoscopes reach in the middle of their range;
yellow up to the operator warning (:data:`WARN_PERCENT`); red beyond it."""

PATCH_PX = 15
"""Side of the correlation patch of the automatic search in the other half (px, odd)."""

DENSE_WINDOW_PX = 31
"""Side of the dense search's plane-sweep window (px, odd; ``--window``): the coarse depth
that starts the refinement. Fronto-parallel planes only fit a curved or tilted surface over
a small window; weak texture is the refinement's job (:data:`DENSE_WINDOW_RANGE_PX`)."""

DENSE_WINDOW_RANGE_PX = (15, 63)
"""Smallest and largest side of the dense refinement's windows (px, odd). A surface pixel
has no mark to lock on: its precision is the texture's derivative energy against the
noise, summed over the window (sigma ~ 1 / side), while the depth is an average over the
window. Each pixel therefore gets the largest window that agrees with all smaller ones
(the intersection of confidence intervals): large where the surface is smooth on that
scale, small at a pit or an edge. 15 px still holds enough samples for a correlation
about a plane. Up to 127 px the largest window's depths carry more error than their
sigma (its start surface's shape error grows with it): compare
``bench/accuracy_dense.py --no-write --window-range 15,127`` with the default's section in
``docs/accuracy.md``; the random designs check the choice (``--designs``)."""

PROFILE_WINDOW_RANGE_PX = (15, 31)
"""The refinement's windows for depth profiles (px, odd): a profile is read at its
extreme, the bottom of a pit or dent, where a window wider than the feature averages it
away. The window choice stops growing where a larger window disagrees beyond the smaller
ones' noise, but a pit a few windows wide can hide inside that noise: compare
``bench/accuracy_profile.py --no-write --window-range 15,63`` with the profile section of
``docs/accuracy.md`` (the default preset's planted pits, radius 11-33 px, and the random
designs' with ``--designs``)."""

ZONE_MM = 5.0
"""Width of the distance zones of the board test (mm): the paper's Fig. 4 uses zones of
a few mm, wide enough for several images per zone and a per-zone standard deviation."""

ALL_MODELS = "all"
"""The ``--model`` value that asks for every registered model."""

# ----- limits checked before any work -------------------------------------------------------

MAX_IMAGE_SIDE = 16384
"""Largest image width or height accepted (px). Videoscope sensors are at most a few
thousand pixels wide; 16384 is several times that, and a common per-side limit of image
codecs. Checked from the file header before any pixel is decoded."""

MAX_IMAGE_PIXELS = 100_000_000
"""Largest image area accepted (px): 100 MP of 8-bit colour decode to 300 MB, and the
detector needs a few such buffers; beyond it a refusal is cheaper than running out of
memory halfway through."""

MAX_WORKERS_PER_CPU = 4
"""``--workers`` may be at most this many times ``os.cpu_count()``: more processes than
that only add memory (each holds decoded images) and start-up time, never speed."""

MAX_MC_SAMPLES = 10_000_000
"""Most Monte Carlo samples (``--samples``): the quantiles are stable to 0.1 % at 1e6;
1e7 still fits in memory for a handful of points."""

MAX_MAP_POINTS = 1_000_000
"""Most grid points of an error map (``--grid`` NU x NV times the depth planes): a
million unscented transforms take minutes; a larger map is not readable in a plot."""

MAX_MAP_DEPTHS = 1000
"""Most depth planes of an error map (``--depths``): far more than a plot can show."""

MIN_ZONE_MM = 0.01
"""Narrowest board-test zone (``--zone-mm``, mm): the test images are taken in steps of
about 1 mm, so zones much narrower than that hold one image each, or none."""

MAX_PATCH_PX = 201
"""Largest correlation patch side (``--patch``, px, odd): wider than a few percent of a
half, a patch spans depth changes and the search no longer localises a point."""

MAX_POINTS_PER_MEASUREMENT = 1000
"""Most points in one measurement (a polyline or an area outline): far more than an
operator clicks, few enough that the unscented transform's sigma points stay fast."""

MAX_SIGMA_PX = 100.0
"""Largest image noise (``--sigma``, px): detected corners scatter by well under a pixel;
at a hundred pixels (a sixth of a half) no propagation of the noise means anything."""

MAX_STORED_ELEMENTS = 50_000_000
"""Most elements of any array a session stores besides images (checked against the
dataset's declared shape before it is read): the largest, a calibration's per-corner
residuals and covariances, hold a few million; 5e7 float64 are 400 MB."""
