"""The stage contract (stages/__init__.py): keyed units skipped once registered, registered with
what they made; every module of stages/ a stage with a documented run_<stage> returning a StageResult."""

import importlib
import inspect
import pkgutil
import typing

import pytest

import stages
from stages import StageResult, StageUnits, UnitOutput
from warehouse.catalog import Catalog


@pytest.fixture
def units(tmp_path) -> StageUnits:
    catalog = Catalog(tmp_path / "warehouse" / "catalog.duckdb")
    catalog.initialise()
    return StageUnits(catalog, "filter", "contract", 0)


def test_a_unit_runs_once_and_is_registered_with_its_summary(units):
    calls = []

    def work() -> UnitOutput:
        calls.append(1)
        return UnitOutput({"kept": 3}, value="made")

    first = units.run("filter-aaa", work)
    again = units.run("filter-aaa", work)
    assert first.value == "made" and again is None and calls == [1]
    [(stage, summary)] = units.catalog.query("SELECT stage, summary FROM stage_runs WHERE unit_key = 'filter-aaa'")
    assert stage == "filter" and '"kept": 3' in summary


def test_a_failing_unit_registers_nothing_and_runs_again(units):
    def broken() -> UnitOutput:
        raise RuntimeError("killed mid-unit")

    with pytest.raises(RuntimeError):
        units.run("filter-bbb", broken)
    assert units.pending(["filter-bbb"]) == ["filter-bbb"]
    assert not units.catalog.query("SELECT count(*) FROM stage_runs WHERE unit_key = 'filter-bbb'")[0][0]
    assert units.run("filter-bbb", lambda: UnitOutput({})) is not None
    assert units.catalog.is_registered("filter-bbb")
    assert units.catalog.query("SELECT count(*) FROM stage_runs WHERE unit_key = 'filter-bbb'") == [(1,)]


def test_pending_keeps_the_order_given_and_leaves_out_registered_keys(units):
    units.register("filter-b", UnitOutput({}), wall_s=0.0)
    assert units.pending(["filter-c", "filter-b", "filter-a"]) == ["filter-c", "filter-a"]


STAGE_MODULES = sorted(m.name for m in pkgutil.iter_modules(stages.__path__))


def test_stages_holds_the_stages_and_nothing_else():
    assert STAGE_MODULES == ["adapt", "baselines", "evaluate", "explore", "filter", "generate_tasks", "index",
                             "redeploy", "train"]


@pytest.mark.parametrize("name", STAGE_MODULES)
def test_every_stage_has_a_documented_entry_point_that_returns_a_stage_result(name):
    module = importlib.import_module(f"stages.{name}")
    assert module.STAGE == name
    run = getattr(module, f"run_{name}")
    doc = inspect.getdoc(run) or ""
    assert "Unit of work" in doc and "egisters" in doc, f"run_{name}'s docstring says no unit or registration"
    returned = typing.get_type_hints(run, vars(module))["return"]
    assert issubclass(returned, StageResult)
    assert returned.did_work is not StageResult.did_work, f"{returned.__name__} does not say whether it did work"


def test_a_result_with_nothing_done_logs_nothing():
    from stages.filter import FilterResult
    from stages.index import IndexResult

    assert FilterResult(unit_keys=["k"], reasons={}, skipped_units=1).metrics() == {}
    skipped = IndexResult(unit_key="k", iteration=0, dataset_digest="d", explore_units=[], filter_units=[], episodes=2,
                          kept_episodes=1, triplets=9, skipped=True)
    assert skipped.metrics() == {} and skipped.tags() == {}
    done = skipped.model_copy(update={"skipped": False})
    assert done.metrics()["dataset.triplets"] == 9 and done.tags() == {"sim2act.dataset_digest": "d"}
    assert FilterResult(unit_keys=["k"], reasons={"kept": 3, "low_return": 1}, skipped_units=0).metrics() == {
        "filter.pass_rate": 0.75, "filter.kept": 3, "filter.low_return": 1}
