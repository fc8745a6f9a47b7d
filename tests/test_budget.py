import pytest

from octomerge_jax import budget


def test_parse_budget_units_and_fractions():
    assert budget.parse_budget("2G") == 2 << 30
    assert budget.parse_budget("512MiB") == 512 << 20
    assert budget.parse_budget("1000") == 1000
    assert budget.parse_budget("0.5") == budget.physical_memory() // 2
    for bad in ("", "abc", "-1", "0", "nan", "inf", "1_0G", "1.5.2"):
        with pytest.raises(ValueError, match="memory budget"):
            budget.parse_budget(bad)


def test_check_allocation_refuses_over_budget_and_nan():
    with budget.memory_budget("1M"):
        budget.check_allocation(1 << 20, "fits")
        with pytest.raises(budget.MemoryBudgetError, match=r"^big map needs 2\.0 MiB, over the memory budget of 1\.0 MiB"):
            budget.check_allocation(2 << 20, "big map")
        with pytest.raises(MemoryError):
            budget.check_allocation(float("nan"), "nan size")
    budget.check_allocation(2 << 20, "outside the context")


def test_environment_variable(monkeypatch):
    monkeypatch.setenv("OCTOMERGE_MEMORY_BUDGET", "3K")
    assert budget.current_budget() == 3072
    monkeypatch.setenv("OCTOMERGE_MEMORY_BUDGET", "lots")
    with pytest.raises(ValueError, match="OCTOMERGE_MEMORY_BUDGET"):
        budget.current_budget()
