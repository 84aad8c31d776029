"""A VLM explorer: any OpenAI-compatible multimodal chat endpoint sees the frame and the instruction
and answers a JSON action, one request per step (docs/explorers.md).

Navigation answers {"action": <a discrete action name>}; manipulation (robosuite, MetaWorld) answers
{"delta": [dx, dy, dz] in [-1, 1], "gripper": "open" | "close"}, mapped onto the shared 7-d action
with zero rotation. An answer off the schema is counted and replaced by a no-op, up to the config's
budget; an endpoint that stays unreachable raises, and the explore stage fails that episode's unit
(redone on resume).
"""

from __future__ import annotations

import base64
import io
import json
import logging
from collections import Counter
from typing import Annotated, Literal

import numpy as np
from PIL import Image
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from envs.observation import ACTION_DIM, Observation
from envs.observation import NAVIGATION_ACTIONS as ACTIONS
from policies.openai_chat import ChatUnavailable, Failure, complete
from schemas.config import VlmExplorerConfig
from schemas.tasks import FAMILIES

log = logging.getLogger("sim2act.policies.vlm_explorer")

STATS = ("steps", "calls", "retries", "timeouts", "http_errors", "connection_errors", "malformed_replies",
         "invalid_answers", "fallback_actions")
_FAILURE_STAT: dict[Failure, str] = {"timeout": "timeouts", "http_error": "http_errors",
                                     "unreachable": "connection_errors", "malformed": "malformed_replies"}
# The navigation env has no stop action; turning in place is the one that moves the agent nowhere.
NAVIGATION_NO_OP = "turn_left"
OPEN, CLOSE = -1.0, 1.0  # the gripper command (envs/observation.py: > 0 closes)
Unit = Annotated[float, Field(ge=-1.0, le=1.0)]


class TooManyInvalidAnswers(RuntimeError):
    pass


# strict: "0.5" is not a number nor true a 1; extra keys (a model's "reason") are ignored.
class NavigationAnswer(BaseModel):
    model_config = ConfigDict(strict=True)

    action: Literal[ACTIONS]  # type: ignore[valid-type]  # the env's names


class ManipulationAnswer(BaseModel):
    model_config = ConfigDict(strict=True)

    delta: tuple[Unit, Unit, Unit]
    gripper: Literal["open", "close"]


_MEANING = {
    NavigationAnswer: ("forward and backward drive, turn_left and turn_right turn in place", '{"action": "forward"}'),
    ManipulationAnswer: ("delta moves the gripper along x, y, z (1 is the largest step); gripper opens or closes "
                         "its fingers", '{"delta": [0.0, 0.0, -0.5], "gripper": "open"}'),
}


TWO_VIEWS = " The image is two views side by side: the scene's camera left, the camera in the robot's hand right."


def png_data_url(image: np.ndarray) -> str:
    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image)).save(buffer, format="PNG")
    return "data:image/png;base64," + base64.b64encode(buffer.getvalue()).decode()


class VlmExplorer:
    """One episode's explorer: build one per episode, so stats() counts that episode."""

    def __init__(self, config: VlmExplorerConfig, family: str, instruction: str):
        if family not in FAMILIES:
            raise ValueError(f"VLM explorer: unknown family {family!r}")
        self.config, self.family, self.instruction = config, family, instruction
        self.answer = NavigationAnswer if family == "navigation" else ManipulationAnswer
        meaning, example = _MEANING[self.answer]
        self.system = ("You control a robot from its camera image. Answer with one JSON object only, matching this "
                       f"JSON schema: {json.dumps(self.answer.model_json_schema())}; {meaning}. Example: {example}")
        self.gripper = OPEN  # episodes start with the gripper open; a no-op keeps the last command
        self.counts: Counter[str] = Counter(dict.fromkeys(STATS, 0))

    def stats(self) -> dict[str, int]:
        return dict(self.counts)

    def messages(self, image: np.ndarray) -> list[dict]:
        two_views = image.shape[1] == 2 * image.shape[0]  # render.wrist_camera: schemas/frames.py
        return [
            {"role": "system", "content": self.system + (TWO_VIEWS if two_views else "")},
            {"role": "user", "content": [
                {"type": "text", "text": f"Instruction: {self.instruction}\nYour next action?"},
                {"type": "image_url", "image_url": {"url": png_data_url(image)}},
            ]},
        ]

    def act(self, obs: Observation) -> np.ndarray:
        if obs.image.size == 0:
            raise ValueError("VLM explorer: the observation has no image (the campaign renders no camera)")
        self.counts["steps"] += 1
        try:
            reply = complete(self.config, self.messages(obs.image), who="VLM explorer",
                             max_tokens=self.config.max_tokens)
        except ChatUnavailable as exc:
            self._count(exc.failures, answered=False)
            if exc.failures[-1] != "malformed":  # unreachable, timed out or refused: the episode fails
                raise
            return self._fallback(str(exc))
        self._count(reply.failures, answered=True)
        try:
            answer = self.answer.model_validate_json(reply.content)
        except ValidationError as exc:  # not JSON, wrong keys or types, out of range, unknown action
            self.counts["invalid_answers"] += 1
            return self._fallback(f"invalid answer {reply.content[:200]!r}: {exc.errors()[0]['msg']}")
        return self._action(answer)

    def _count(self, failures: list[Failure], answered: bool) -> None:
        calls = len(failures) + answered
        self.counts["calls"] += calls
        self.counts["retries"] += calls - 1
        self.counts.update(_FAILURE_STAT[kind] for kind in failures)

    def _fallback(self, why: str) -> np.ndarray:
        self.counts["fallback_actions"] += 1
        if self.counts["fallback_actions"] > self.config.max_invalid_answers:
            raise TooManyInvalidAnswers(
                f"VLM explorer: {self.counts['fallback_actions']} unusable answers this episode, over "
                f"explore.vlm.max_invalid_answers={self.config.max_invalid_answers}; last: {why}")
        log.debug("VLM explorer: no-op for %s", why)
        return self._action(None)

    def _action(self, answer: NavigationAnswer | ManipulationAnswer | None) -> np.ndarray:
        """The family's action for an answer; for None the no-op: navigation turns in place,
        manipulation holds still with the gripper as last commanded."""
        if self.family == "navigation":
            name = answer.action if isinstance(answer, NavigationAnswer) else NAVIGATION_NO_OP
            return np.array([ACTIONS.index(name)], dtype=np.float32)
        action = np.zeros(ACTION_DIM, dtype=np.float32)  # rotation deltas stay 0
        if isinstance(answer, ManipulationAnswer):
            self.gripper = CLOSE if answer.gripper == "close" else OPEN
            action[:3] = answer.delta
        action[-1] = self.gripper
        return action
