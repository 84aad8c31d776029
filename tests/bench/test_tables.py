"""The benches' one table writer and their ratios."""

from bench.tables import Ratio, ratio_table, table


def test_a_ratio_is_met_on_the_side_its_target_says():
    assert Ratio.of("speed", 1.07, 1.8).met is False and Ratio.of("speed", 1.9, 1.8).met is True
    assert Ratio.of("wait", 0.026, 0.10, "%", at_most=True).met is True
    assert Ratio.of("plain", 1.15).met is None


def test_tables_leave_missing_cells_empty_and_show_units():
    assert table(["a", "b"], [[1, None]]) == ["| a | b |", "|---|---|", "| 1 |  |"]
    lines = ratio_table([Ratio.of("wait", 0.026, 0.10, "%", at_most=True), Ratio.of("p95", 8.0, 20.0, "ms", True)])
    assert lines[2] == "| wait | 2.6% | <= 10.0% | ✓ |" and lines[3] == "| p95 | 8.0 ms | <= 20.0 ms | ✓ |"
