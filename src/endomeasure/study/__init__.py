"""Design studies (``endomeasure sweep``): a sweep spec and the pure evaluation of one
probe design from it (simulated calibration corners, calibration, error map).

:mod:`.spec` reads and validates the spec and expands its designs; :mod:`.evaluate`
evaluates one design, a pure function of the spec and the design's index;
:mod:`.results` ranks the evaluated designs and finds the Pareto front. Execution (Dask,
the results file) is the pipeline's business, so everything here runs the same in any
process.
"""
