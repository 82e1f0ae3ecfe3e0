"""tools/bench_heuristics.py on a short stretch of the packaged sample: both ways run and the line is printed (no
timing asserted)."""

from __future__ import annotations

import importlib.util

from conftest import ROOT


def test_the_benchmark_prints_both_ways_for_each_heuristic(capsys) -> None:
    spec = importlib.util.spec_from_file_location("bench_heuristics", ROOT / "tools" / "bench_heuristics.py")
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    assert bench.main(["--rounds", "2"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 3 and all("a push per sample" in ln and "blocks of 10" in ln for ln in lines[1:])
    assert {ln.split()[0] for ln in lines[1:]} == {"deceleration", "reference_pillar"}
