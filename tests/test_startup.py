"""The fixed-cost benchmark (python -m tuning.benchmark.startup): its machinery, on the cheap
case."""

from tuning.benchmark import startup


def test_import_case_measures_both_imports():
    result = startup.measure(("import",), repeats=1)
    rows = result["import"]
    assert set(rows) == {"jax", "jaxcart"}
    assert all(row["wall"] > 0 and len(row["runs"]) == 1 for row in rows.values())
    assert "import" in startup.table(result)


def test_reported_times_are_read_from_the_commands_output():
    tune_text = (
        "39 iterations x 8 starts in 2.1 s (compilation included); "
        "first gains meeting it after 0.7 s"
    )
    assert startup._reported("tune", tune_text) == 0.7
    assert startup._reported("fit-tap", "correlation B_eq, f_c: -0.994\nfitted in 3.6 s\n") == 3.6
    assert startup._reported("fit-p50", "no time here") is None
