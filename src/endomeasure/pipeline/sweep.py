"""``endomeasure sweep``: evaluate every design of a sweep spec, serially or on Dask.

The spec is validated whole before any work (:func:`~endomeasure.study.spec.read_spec`).
The designs the results file does not hold yet are evaluated
(:func:`~endomeasure.study.evaluate.evaluate_design`, a pure function of the spec and the
index, so the results do not depend on where or in which order they run): in this
process (``workers=0``), on a Dask ``LocalCluster`` of worker processes (one thread
each; ``workers=None``: one per core), or on a running scheduler (``scheduler``: its
address; its workers must import endomeasure). Each result is written to the file as it
arrives, so an interrupted sweep resumes where it stopped. This is the only module that
imports Dask.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from endomeasure.errors import BadInputError

__all__ = ["SweepReport", "run_sweep", "load_results"]


@dataclasses.dataclass(frozen=True)
class SweepReport:
    spec: str
    output: str
    mode: str
    n_designs: int
    computed: list[int]
    skipped: int
    seconds: float
    results: list[Any] = dataclasses.field(repr=False)  # DesignResult, by index
    ranked: list[Any] = dataclasses.field(repr=False)
    pareto: list[Any] = dataclasses.field(repr=False)
    axis_names: tuple[str, ...] = ()
    cost_name: str = ""
    target_pct: float = float("nan")
    plot: str | None = None
    exported: list[str] = dataclasses.field(default_factory=list)

    @property
    def missing(self) -> int:
        return self.n_designs - len(self.results)

    def row(self, r) -> dict[str, Any]:
        return {
            "index": r.index,
            **dict(zip(self.axis_names, map(float, r.values), strict=True)),
            "merit_pct": r.merit,
            "success": r.success,
            "cost": r.cost,
            "meets_target": bool(r.merit <= self.target_pct and r.success == 1.0),
            "status": [int(s) for s in r.status],
            "reasons": [x for x in r.reasons if x],
        }

    def to_dict(self) -> dict[str, Any]:
        return {
            "spec": self.spec,
            "output": self.output,
            "mode": self.mode,
            "n_designs": self.n_designs,
            "computed": self.computed,
            "skipped": self.skipped,
            "missing": self.missing,
            "seconds": self.seconds,
            "cost": self.cost_name,
            "target_pct": self.target_pct,
            "ranked": [self.row(r) for r in self.ranked],
            "pareto": [r.index for r in self.pareto],
            "plot": self.plot,
            "exported": self.exported,
        }


def _serial(spec, todo, store, on_progress, total, done):
    from endomeasure.study.evaluate import evaluate_design

    for index in todo:
        store.append(evaluate_design(spec, index))
        done += 1
        if on_progress:
            on_progress(done, total)


QUIET_CLUSTER = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "5s",
    "distributed.worker.memory.monitor-interval": "1s",
}
"""Dask settings of the local cluster, which its worker processes inherit. A design takes
seconds, so Dask's monitoring at 10-500 ms granularity only takes CPU from the designs:
the statistical profiler (a thread sampling each worker's stacks every 10 ms), the
event-loop ticks (20 ms), the system monitors (500 ms) and the nannies' memory polls
(100 ms). What they cost is in docs/sweep.md, "Throughput"."""


def _client(scheduler: str | None, workers: int | None):
    """A Dask client of the scheduler, or of a new LocalCluster (and the cluster)."""
    import dask
    from distributed import Client, LocalCluster  # loads the distributed.* defaults first

    if scheduler is not None:
        try:
            return Client(scheduler, timeout="10s"), None, f"scheduler {scheduler}"
        except (OSError, TimeoutError, ValueError) as exc:
            raise BadInputError(
                f"cannot reach the Dask scheduler {scheduler} ({exc})",
                hint="give the address `dask scheduler` printed",
            ) from None
    n = workers or os.cpu_count() or 1
    with dask.config.set(QUIET_CLUSTER):
        cluster = LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            dashboard_address=":0",
            silence_logs=logging.ERROR,
        )
    return Client(cluster), cluster, f"local cluster of {n} worker processes"


def _on_dask(spec, todo, store, on_progress, total, done, scheduler, workers) -> str:
    from distributed import as_completed

    from endomeasure.study.evaluate import evaluate_design

    client, cluster, mode = _client(scheduler, workers)
    try:
        spec_future = client.scatter(spec, broadcast=True)
        futures = client.map(
            evaluate_design,
            [spec_future] * len(todo),
            todo,
            key=[f"sweep-{spec.digest[:12]}-{i}" for i in todo],
        )
        for future in as_completed(futures):
            store.append(future.result())
            future.release()
            done += 1
            if on_progress:
                on_progress(done, total)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return mode


def load_results(output: str | Path, spec) -> list[Any]:
    """The designs a results file holds, as ``DesignResult`` by index."""
    from endomeasure.io.sweep_results import SweepResultsFile
    from endomeasure.study.evaluate import DesignResult

    store = SweepResultsFile(
        output, json.dumps(spec.document), spec.digest, spec.n_designs, spec.axis_names
    )
    return [DesignResult(**row) for row in store.read_all()]


def _export(spec, index: int, folder: Path) -> list[str]:
    """The nominal preset of design ``index`` (for ``simulate --preset``) and its truth
    model file (for ``predict-error --map --model-file``)."""
    from endomeasure.io.export import model_document, write_json_document
    from endomeasure.simulate.preset import Preset

    if not 0 <= index < spec.n_designs:
        raise BadInputError(f"--export {index}: the sweep has designs 0-{spec.n_designs - 1}")
    data = spec.design_preset(index)
    folder.mkdir(parents=True, exist_ok=True)
    preset_path = write_json_document(data, folder / f"design-{index}.preset.json")
    model = Preset.from_dict(data).truth_model
    model_path = write_json_document(model_document(model), folder / f"design-{index}.model.json")
    return [str(preset_path), str(model_path)]


def run_sweep(
    spec_path: str | Path,
    output: str | Path,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    max_designs: int | None = None,
    on_progress: Callable[[int, int], None] | None = None,
    plot: str | Path | None = None,
    export: int | None = None,
    export_dir: str | Path | None = None,
) -> SweepReport:
    """Evaluate the designs of ``spec_path`` that ``output`` lacks, and summarise all.

    ``workers``: 0 serial, None one worker process per core, N that many (ignored with
    ``scheduler``); ``max_designs``: evaluate at most this many now (the rest on a
    rerun); ``on_progress(done, total)`` after each design; ``plot``: a figure of the
    merit against the cost and over the axes; ``export``: a design index whose preset
    and model file go to ``export_dir`` (default: the output's folder).
    """
    from endomeasure.io.outputs import PLOT_SUFFIXES, checked_outputs
    from endomeasure.io.sweep_results import SweepResultsFile
    from endomeasure.study.results import pareto_front, plot_sweep, ranked
    from endomeasure.study.spec import read_spec

    if workers is not None and workers < 0:
        raise BadInputError(f"--workers must be 0 (serial) or more, not {workers}")
    if max_designs is not None and max_designs < 0:
        raise BadInputError(f"--max-designs must be 0 or more, not {max_designs}")
    spec = read_spec(spec_path)
    output, plot = checked_outputs(
        [(output, "results file", (".h5", ".hdf5")), (plot, "plot", PLOT_SUFFIXES)],
        inputs=[spec_path],
    )
    store = SweepResultsFile(
        output, json.dumps(spec.document), spec.digest, spec.n_designs, spec.axis_names
    )
    finished = store.finished()
    todo = [i for i in range(spec.n_designs) if i not in finished]
    if max_designs is not None:
        todo = todo[:max_designs]
    t0 = time.perf_counter()
    mode = "serial" if workers == 0 and scheduler is None else "dask"
    if not todo:
        mode = "nothing to compute"
    elif mode == "serial":
        _serial(spec, todo, store, on_progress, spec.n_designs, len(finished))
    else:
        mode = _on_dask(
            spec, todo, store, on_progress, spec.n_designs, len(finished), scheduler, workers
        )
    seconds = time.perf_counter() - t0
    results = load_results(output, spec)
    written = None if plot is None or not results else str(plot_sweep(spec, results, plot))
    exported = []
    if export is not None:
        exported = _export(spec, int(export), Path(export_dir or Path(output).parent))
    return SweepReport(
        str(spec_path),
        str(output),
        mode,
        spec.n_designs,
        todo,
        len(finished),
        seconds,
        results,
        ranked(results),
        pareto_front(results),
        spec.axis_names,
        spec.cost,
        spec.target_pct,
        written,
        exported,
    )
