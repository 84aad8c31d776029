"""`sim2act config`: the campaign the options name as commented YAML, which `--config` loads back to the same
campaign (every preset, whole or only what differs from the default preset)."""

from __future__ import annotations

import pytest
import yaml

from flows.cli import main
from schemas.config import PRESETS, load_config
from schemas.config_text import config_yaml


@pytest.mark.parametrize("preset", PRESETS)
@pytest.mark.parametrize("changed", [False, True], ids=["whole", "changed"])
def test_the_yaml_loads_back_to_the_same_campaign(tmp_path, preset, changed):
    config = load_config(preset, None, {"evaluate": {"max_steps": 7}, "baselines": {"env_steps": {"metaworld": 900}}})
    text = config_yaml(config, changed=changed)
    (tmp_path / "campaign.yaml").write_text(text)
    assert load_config("default", tmp_path / "campaign.yaml") == config
    if not changed:  # every field is written, each value as the config holds it
        assert yaml.safe_load(text) == config.model_dump(mode="json")
    else:  # and only those that differ from the default preset
        assert "max_steps: 7" in text and "seed:" not in text


def test_each_field_is_said_above_its_value_and_each_section_under_its_models_first_line():
    lines = config_yaml(load_config("smoke")).splitlines()
    at = lines.index("  max_steps: null")
    assert lines[at - 3].startswith("  # end every evaluation episode after at most this many steps")
    assert lines[lines.index("baselines:") - 1] == "# What the campaign is measured against, after its last iteration " \
                                                 "(stages.baselines)."
    assert max(len(line) for line in lines if line.lstrip().startswith("#")) <= 110
    # a long list goes on over lines deeper than its key, which YAML reads as one list
    specs = config_yaml(load_config("generalist")).splitlines()
    start = next(i for i, line in enumerate(specs) if line.startswith("  specs: ["))
    assert specs[start + 1].startswith("      ") and len(yaml.safe_load("\n".join(specs))["tasks"]["specs"]) > 60


def test_sim2act_config_prints_it_and_refuses_a_bad_field_in_one_line(capsys):
    assert main(["config", "--preset", "smoke", "--set", "train.steps=3", "--changed"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("# sim2act config --preset smoke --set train.steps=3 --changed\n")
    assert yaml.safe_load(out)["train"]["steps"] == 3
    assert main(["config", "--set", "train.stepz=3"]) == 2
    assert capsys.readouterr().err.strip() == "sim2act: config error: train.stepz: unknown key"


def test_every_config_field_says_what_it_does():
    """robomimic's rule: a field a person reads in `sim2act config` (or the Prefect UI's form) comes with its purpose."""
    import typing

    from pydantic import BaseModel

    from schemas.config import CampaignConfig

    def silent(model: type[BaseModel], prefix: str = "") -> list[str]:
        found = []
        for name, field in model.model_fields.items():
            nested = [a for a in (field.annotation, *typing.get_args(field.annotation))
                      if isinstance(a, type) and issubclass(a, BaseModel)]
            if nested:
                found += [path for sub in nested for path in silent(sub, f"{prefix}{name}.")]
            elif not field.description:
                found.append(prefix + name)
        return found

    assert silent(CampaignConfig) == []
