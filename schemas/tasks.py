"""Language-described task records: what generate_tasks produces and every later stage reads."""

from __future__ import annotations

from typing import Literal, get_args

from pydantic import BaseModel, ConfigDict, Field

Colour = Literal["red", "green", "blue", "yellow", "purple", "orange"]

# Flat colours for the task objects (the material/texture is dropped so the colour is what the camera sees).
COLOUR_RGBA: dict[str, tuple[float, float, float, float]] = {
    "red": (0.85, 0.12, 0.10, 1.0),
    "green": (0.15, 0.70, 0.20, 1.0),
    "blue": (0.12, 0.25, 0.85, 1.0),
    "yellow": (0.92, 0.85, 0.12, 1.0),
    "purple": (0.55, 0.20, 0.70, 1.0),
    "orange": (0.95, 0.50, 0.08, 1.0),
}

Split = Literal["seen", "unseen"]
# Evaluations add a third: a seen task said with one of its held-out paraphrases.
UNSEEN_PARAPHRASE = "unseen_paraphrase"
CAMPAIGN_SUITE = "campaign"  # evaluations.suite of the flow's own evaluation (`sim2act eval` names others)
Family = Literal["robosuite", "metaworld", "navigation"]
FAMILIES: tuple[str, ...] = get_args(Family)
# Steps a second, one action (and one stored frame) a step: robosuite's control_freq, MetaWorld's frame_skip 5 of
# 2.5 ms physics steps, navigation's 0.1 s (envs/*_env.py). Videos and LeRobot datasets play at these.
CONTROL_HZ = {"robosuite": 20, "metaworld": 80, "navigation": 10}


class TaskRecord(BaseModel):
    """One concrete task: an environment, object attributes, and the ways to say it."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    task_id: str
    spec: str
    family: Family
    env_name: str
    # object role -> colour, e.g. {"target": "red"} or {"pick": "red", "place": "green"}
    object_colours: dict[str, Colour]
    instructions: list[str] = Field(min_length=3, description="first is canonical, the rest paraphrases")
    split: Split
    unseen_instructions: list[str] = Field(default=[], description="held-out paraphrases, for evaluation only")
    horizon: int = Field(gt=0)

    @property
    def instruction(self) -> str:
        return self.instructions[0]
