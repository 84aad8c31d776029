"""Declarative task specs: a YAML file a user writes to add tasks. One spec expands into one
task per binding of colours to its object roles, each said in several ways.

A file holds `specs:` (a list) and optional `defaults:` merged into every spec. Whether the
environment and its roles exist is checked against the simulator adapters (envs.registry),
since schemas import nothing of ours.
"""

from __future__ import annotations

import string
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from schemas.config import ConfigError, describe_validation_error, load_yaml, read_text_file, yaml_error_said
from schemas.tasks import Colour, Family

BUILTIN_FILES = ("robosuite.yaml", "metaworld.yaml", "navigation.yaml")


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ObjectSpec(_Strict):
    colours: list[Colour] = Field(min_length=1)


class SplitSpec(_Strict):
    """What is held out: any binding that uses an unseen colour, whole tasks by id, and ways of
    saying a task (templates never explored or trained on, only evaluated)."""

    unseen_colours: list[Colour] = []
    unseen_tasks: list[str] = []
    unseen_templates: list[str] = []


class SubtaskSpec(_Strict):
    """One step of a long-horizon task: another spec, its roles bound to this spec's."""

    spec: str
    objects: dict[str, str] = Field(description="the sub-spec's role -> this spec's role whose colour it takes")


class TaskSpec(_Strict):
    name: str = Field(pattern=r"^[a-z0-9][a-z0-9-]*$")
    family: Family
    env: str
    objects: dict[str, ObjectSpec] = {}
    templates: list[str] = Field(min_length=3, description="language templates; {role} is replaced by its colour")
    success: Literal["env"] = Field(default="env", description="'env': the environment's own success check")
    horizon: int = Field(gt=0)
    expert: Literal["pick_place", "open_door", "metaworld_policy", "navigation_planner"]
    split: SplitSpec = SplitSpec()
    subtasks: list[SubtaskSpec] = Field(
        default=[], description="long-horizon: the sub-tasks whose goals the task reaches in order (a curriculum "
        "learns it from them: explore.curriculum)",
    )

    @model_validator(mode="after")
    def _templates_name_roles(self) -> TaskSpec:
        for template in [*self.templates, *self.split.unseen_templates]:
            fields = {name for _, name, _, _ in string.Formatter().parse(template) if name is not None}
            if "" in fields or any(name.isdigit() for name in fields):
                raise ValueError(f"template {template!r} has a positional field: name a role, e.g. {{target}}")
            unknown = sorted(fields - set(self.objects))
            if unknown:
                raise ValueError(f"template {template!r} names {unknown}, which are not in objects")
            unsaid = sorted(set(self.objects) - fields)
            if unsaid:  # tasks that differ only in that role's colour would be said alike
                raise ValueError(f"template {template!r} does not name {unsaid}: every template names every role")
        for sub in self.subtasks:
            unknown = sorted(set(sub.objects.values()) - set(self.objects))
            if unknown:
                raise ValueError(f"subtasks: {sub.spec} takes the colour of {unknown}, which are not in objects")
        shared = sorted(set(self.templates) & set(self.split.unseen_templates))
        if shared:
            raise ValueError(f"template {shared[0]!r} is both seen and held out (split.unseen_templates)")
        return self


class TaskSpecFile(_Strict):
    specs: list[TaskSpec] = Field(min_length=1)


def parse_spec_file(text: str, origin: str) -> list[TaskSpec]:
    """Parse and validate one file; a broken one raises ConfigError naming the field and reason."""
    try:
        data = load_yaml(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{origin}: not valid YAML ({yaml_error_said(exc)})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{origin}: expected a mapping with 'specs:' (and optional 'defaults:')")
    defaults: dict[str, Any] = data.pop("defaults", None) or {}
    if "specs" in data and isinstance(data["specs"], list):
        data["specs"] = [{**defaults, **spec} if isinstance(spec, dict) else spec for spec in data["specs"]]
    try:
        specs = TaskSpecFile.model_validate(data).specs
    except ValidationError as exc:
        raise ConfigError(f"{origin}: {describe_validation_error(exc)}") from None
    names = [s.name for s in specs]
    duplicate = next((n for n in names if names.count(n) > 1), None)
    if duplicate:
        raise ConfigError(f"{origin}: spec name {duplicate!r} appears twice")
    return specs


@dataclass(frozen=True)
class SuiteEntry:
    spec: TaskSpec
    origin: str  # the file it came from, for error messages


def builtin_spec_file(path: Path) -> bool:
    """`path` is one of the built-in suite's own spec files."""
    folder = resources.files("schemas").joinpath("task_specs")
    return any(Path(str(folder.joinpath(name))).resolve() == Path(path).resolve() for name in BUILTIN_FILES)


def load_specs(extra_files: list[Path] = ()) -> dict[str, SuiteEntry]:
    """The built-in suite plus the user's files, by spec name."""
    specs: dict[str, SuiteEntry] = {}
    folder = resources.files("schemas").joinpath("task_specs")
    sources = [(folder.joinpath(name).read_text(), f"task_specs/{name}") for name in BUILTIN_FILES]
    for path in extra_files:
        if not Path(path).is_file():
            raise ConfigError(f"tasks.spec_files: expected a YAML spec file, got "
                              f"{'the folder ' if Path(path).is_dir() else 'no such file '}{path}")
        sources.append((read_text_file(Path(path), "tasks.spec_files"), str(path)))
    for text, origin in sources:
        for spec in parse_spec_file(text, origin):
            if spec.name in specs:
                raise ConfigError(f"{origin}: spec name {spec.name!r} is already defined (in {specs[spec.name].origin}): "
                                  "give yours another name")
            specs[spec.name] = SuiteEntry(spec, origin)
    for entry in specs.values():
        for sub in entry.spec.subtasks:
            if sub.spec not in specs:
                raise ConfigError(f"{entry.origin}: {entry.spec.name}.subtasks: unknown spec {sub.spec!r}")
            roles = set(specs[sub.spec].spec.objects)
            if set(sub.objects) != roles:
                raise ConfigError(f"{entry.origin}: {entry.spec.name}.subtasks: {sub.spec} has roles {sorted(roles)}, "
                                  f"the sub-task binds {sorted(sub.objects)}")
    return specs
