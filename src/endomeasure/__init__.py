"""endomeasure: 3D measurement with prism-based stereo video endoscopes.

The package is layered (arrows point to what a layer may import)::

    cli -> pipeline -> {io, features, simulate, measure, solvers} -> models -> geometry -> conventions

Only ``cli`` imports typer/rich and only ``io`` imports h5py; the core never prints.
"""

__version__ = "0.1.0"
