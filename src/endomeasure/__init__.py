"""endomeasure: 3D measurement with prism-based stereo video endoscopes.

The package is layered (arrows point to what a layer may import)::

    cli -> pipeline -> {io, features, simulate, measure, solvers}
        -> models -> geometry -> conventions

Only ``cli`` imports typer/rich and only ``io`` imports h5py; the core never prints.
"""

import os as _os

# Our linear algebra is on small matrices (tens of parameters, 2x2 and 3x3 blocks), where
# a threaded BLAS only adds contention: on a loaded 2-core machine a 15000x30 product took
# 0.6-0.9 s with OpenBLAS threads and 2 ms without. Single-threaded by default; a value
# the user set wins. This must run before numpy is first imported to take effect.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")

__version__ = "0.1.0"
