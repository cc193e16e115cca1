"""The benchmark and accuracy scripts' shared entry (bench/_common.py), without running a
script: the common options, the target checks, the exit status and the docs section a
missed target leaves behind."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from tests.bench.bench_scripts import load_bench_script

common = load_bench_script("_common.py", "bench_common")
UNDER_1_S = common.Target("ML triangulation", "<", 1.0, " s", "issue 7")
SECTION = "triangulate"
DOC_BEFORE = (
    f"# Benchmarks\n\nhand-written\n\n<!-- begin {SECTION} -->\nold\n<!-- end {SECTION} -->\n"
)


def _run(tmp_path: Path, value: float, *flags: str) -> tuple[int, str]:
    """One 'script' run: parse the common flags, check a value, finish; (status, doc)."""
    doc = tmp_path / "benchmarks.md"
    doc.write_text(DOC_BEFORE)
    args = common.script_parser("A script.\n\nMore text.", seed=3).parse_args(list(flags))
    report = common.Report("bench/bench_x.py", args, doc)
    check = report.check(UNDER_1_S, value)
    status = report.finish({SECTION: f"## Triangulation\n\nthis run: {check}."})
    return status, doc.read_text()


def test_met_target_exits_zero_and_writes_the_section(tmp_path):
    status, doc = _run(tmp_path, 0.5)
    assert status == 0
    assert "this run: met." in doc
    assert "Missed" not in doc
    assert "hand-written" in doc and "old" not in doc


def test_missed_target_exits_non_zero_and_the_section_says_so(tmp_path, capsys):
    status, doc = _run(tmp_path, 1.2)
    assert status == common.EXIT_MISSED != 0
    assert "this run: **missed**." in doc
    assert "**Missed in this run:** ML triangulation < 1 s (issue 7) (this run 1.2 s)." in doc
    err = capsys.readouterr().err
    assert "bench/bench_x.py: MISSED: ML triangulation < 1 s (issue 7); this run 1.2 s" in err


def test_no_write_leaves_the_doc_alone(tmp_path):
    status, doc = _run(tmp_path, 1.2, "--no-write")
    assert status == common.EXIT_MISSED
    assert doc == DOC_BEFORE


def test_quick_neither_writes_nor_enforces(tmp_path, capsys):
    status, doc = _run(tmp_path, 1.2, "--quick")
    assert status == 0
    assert doc == DOC_BEFORE
    assert "targets not enforced" in capsys.readouterr().err


def test_a_missed_target_marks_only_its_own_section(tmp_path):
    doc = tmp_path / "accuracy.md"
    doc.write_text("# Accuracy\n")
    args = common.script_parser(None).parse_args([])
    report = common.Report("bench/accuracy_x.py", args, doc)
    report.check(UNDER_1_S, 0.1, section="a")
    report.check(UNDER_1_S, 2.0, section="b")
    assert report.finish({"a": "A", "b": "B"}) == common.EXIT_MISSED
    text = doc.read_text()
    a, b = text.split("<!-- begin b -->")
    assert "Missed" not in a
    assert "**Missed in this run:**" in b


@pytest.mark.parametrize(
    ("op", "value", "met"),
    [("<", 1.0, False), ("<=", 1.0, True), (">", 1.0, False), (">=", 1.0, True),
     ("==", 1.0, True), ("<", 0.99, True), (">=", 0.99, False), ("<=", math.nan, False),
     (">=", math.nan, False)],
)  # fmt: skip
def test_target_comparisons(op, value, met):
    assert common.Target("x", op, 1.0).met_by(value) is met


def test_unknown_comparison_is_refused():
    with pytest.raises(ValueError, match="unknown comparison"):
        common.Target("x", "=<", 1.0)


def test_common_options():
    parser = common.script_parser("Title line.\n\nBody.", seed=7, work=True)
    args = parser.parse_args([])
    assert (args.quick, args.no_write, args.seed, args.work) == (False, False, 7, None)
    args = parser.parse_args(["--quick", "--seed", "2", "--work", "/tmp/w"])
    assert (args.quick, args.seed, args.work) == (True, 2, Path("/tmp/w"))
    assert parser.description == "Title line."
    assert not hasattr(common.script_parser(None).parse_args([]), "seed")


def test_replace_section_keeps_the_text_around_it():
    text = common.replace_section(DOC_BEFORE, SECTION, "new")
    assert text == DOC_BEFORE.replace("\nold\n", "\nnew\n")
    appended = common.replace_section("# T\n", "other", "body")
    assert appended == "# T\n\n<!-- begin other -->\nbody\n<!-- end other -->\n"
