"""The measured scripted-expert success per task: written by `sim2act tasks experts`, shipped
beside the task specs, and read by generate_tasks so that tasks whose expert falls below the
target are flagged and left out of campaigns unless asked for (`tasks.weak_experts: keep`)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from pydantic import BaseModel

from schemas.workspace import write_text_atomically

TARGET = 0.9


def default_table_path() -> Path:
    return Path(str(resources.files("schemas").joinpath("task_specs/experts.json")))


class ExpertRow(BaseModel):
    task_id: str
    family: str
    split: str
    episodes: int
    successes: int
    mean_length: float
    noise: float
    randomised: bool
    command: str  # what measured it
    measured_on: str  # ISO date

    @property
    def success_rate(self) -> float:
        return self.successes / self.episodes

    @property
    def below_target(self) -> bool:
        return self.success_rate < TARGET


class ExpertTable(BaseModel):
    rows: dict[str, ExpertRow] = {}

    def merged(self, rows: list[ExpertRow]) -> ExpertTable:
        """This table with `rows` measured again (a partial run replaces only its own tasks)."""
        return ExpertTable(rows={**self.rows, **{r.task_id: r for r in rows}})

    def flagged(self) -> set[str]:
        return {task_id for task_id, row in self.rows.items() if row.below_target}


def load_expert_table(path: Path | None = None) -> ExpertTable:
    path = path or default_table_path()
    return ExpertTable.model_validate_json(path.read_text()) if path.is_file() else ExpertTable()


def save_expert_table(table: ExpertTable, path: Path | None = None) -> None:
    write_text_atomically(path or default_table_path(), table.model_dump_json(indent=1) + "\n")
