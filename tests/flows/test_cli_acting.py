"""`sim2act shadow --execution/--execute-steps/--ensemble-decay`: a checkpoint acting otherwise than it
trained to, refused in one line before any work where the values do not apply to its model."""

from __future__ import annotations

import pytest

import flows.cli as cli
from flows.cli.campaign import acting_of
from schemas.config import ConfigError, ModelConfig

CHUNK_8 = {"model_config": ModelConfig(chunk=8).model_dump()}  # as a checkpoint holds it: temporal_ensemble


def _acting(*flags: str, state: dict = CHUNK_8):
    return acting_of(cli.build_parser().parse_args(["shadow", "--model", "champion", *flags]), state)


def test_the_flags_make_the_acting_and_none_keeps_the_checkpoints_own():
    assert _acting() is None
    acting = _acting("--execution", "receding", "--execute-steps", "1")
    assert (acting.execution, acting.execute_steps, acting.ensemble_decay) == ("receding", 1, None)
    assert _acting("--ensemble-decay", "0.5").ensemble_decay == 0.5  # the model's own execution: temporal_ensemble
    # receding without a step count takes half the chunk, and says so
    assert _acting("--execution", "receding").describe() == "execution receding, execute_steps 4"


@pytest.mark.parametrize(("flags", "state", "says"), [
    (["--execution", "receding", "--execute-steps", "0"], CHUNK_8,
     "--execute-steps: input should be greater than or equal to 1, got 0"),
    (["--execution", "receding", "--execute-steps", "9"], CHUNK_8,
     "--execute-steps: expected at most the model's chunk (8), got 9"),
    (["--execute-steps", "2"], CHUNK_8, "--execute-steps: applies to --execution receding, got execution temporal_ensemble"),
    (["--execution", "receding", "--ensemble-decay", "0.1"], CHUNK_8,
     "--ensemble-decay: applies to --execution temporal_ensemble, got execution receding"),
    (["--ensemble-decay", "0.1"], {"model_config": ModelConfig(chunk=1).model_dump()},
     "--ensemble-decay: the model predicts one action per observation (chunk 1): it acts one way"),
])
def test_values_that_do_not_apply_are_refused_in_one_line(flags, state, says):
    with pytest.raises(ConfigError) as refused:
        _acting(*flags, state=state)
    assert str(refused.value) == says
