"""bench/accuracy_report.py's own helpers, without running the script: the board sets of
given pixels are the library's."""

from __future__ import annotations

import numpy as np
from tests.bench.bench_scripts import load_bench_script

report = load_bench_script("accuracy_report.py", "accuracy_report")


def _truth(board: str, cols: int, n: int) -> dict:
    return {
        "board_spec": board,
        "target": {"cols": cols, "rows": n // cols, "square_mm": 1.5},
        "corners": {"ids": list(range(n))},
    }


def test_truth_board_sets_keep_every_corner_and_the_first_seen_board_order():
    rng = np.random.default_rng(0)
    images = []
    for name, board in (("a0", "b:2"), ("a1", "b:1"), ("a2", "b:2")):
        truth = _truth(board, 3, 6)
        images.append((name, truth, rng.normal(size=(6, 2)), rng.normal(size=(6, 2))))
    sets = report.truth_board_sets(images)
    assert [(s.board, s.images) for s in sets] == [("b:2", ["a0", "a2"]), ("b:1", ["a1"])]
    assert (sets[0].cols, sets[0].rows, sets[0].square_mm) == (3, 2, 1.5)
    np.testing.assert_array_equal(sets[0].left[1], images[2][2])
    np.testing.assert_array_equal(sets[0].right[0], images[0][3])
    assert sets[1].ids[0].dtype == np.int64 and list(sets[1].ids[0]) == list(range(6))
