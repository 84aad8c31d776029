"""The policy as an MLflow pyfunc model ("models from code"), so the registry holds a loadable,
servable model: this file is logged with the checkpoint as its artifact."""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path
from typing import TYPE_CHECKING

import mlflow.pyfunc
import numpy as np
import pandas as pd
from mlflow.models import set_model

if TYPE_CHECKING:
    from policies.chunking import EpisodeActor

MODEL_CODE = __file__


EPISODES_HELD = 1024  # episodes whose chunks a served model keeps (the least recently acted on go first)


class PolicyModel(mlflow.pyfunc.PythonModel):
    """Input: a DataFrame with `image` (a frame's bytes as the warehouse stores them: schemas.frames),
    `depth` (its depth map's bytes; RGB-D models only), `proprio` (list of floats), `instruction`
    (str), `family` (robosuite, metaworld, navigation), and optionally `episode_id` (str).
    Output: a DataFrame with `action` (list of floats: continuous components, or [index]) and
    `uncertainty` (entropy or log det Sigma).

    With `episode_id`, each episode's rows (in step order, across calls) act as evaluation acts: through
    the chunks predicted earlier in the episode (temporal ensembling or a receding horizon,
    policies/chunking.py), so the served controller is the one whose success rates were measured.
    Without it every row is acted on alone (the first position of its chunk)."""

    def load_context(self, context) -> None:
        from policies.policy import Policy

        self.policy = Policy.load(Path(context.artifacts["checkpoint"]))
        self.episodes: OrderedDict[str, EpisodeActor] = OrderedDict()

    def predict(self, context, model_input: pd.DataFrame, params: dict | None = None) -> pd.DataFrame:
        return predict_frame(self.policy, model_input, self.episodes)


def predict_frame(policy, frame: pd.DataFrame, episodes: OrderedDict | None = None) -> pd.DataFrame:
    """The actions of `frame`'s rows (PolicyModel's input); `episodes` holds each episode's actor across
    calls where the frame has `episode_id`."""
    from envs.observation import Observation
    from schemas.frames import decode_depth, decode_frame

    depths = frame["depth"] if "depth" in frame else [None] * len(frame)
    ids = frame["episode_id"] if "episode_id" in frame and episodes is not None else [None] * len(frame)
    decisions = []
    for image, depth, proprio, instruction, family, episode_id in zip(
            frame["image"], depths, frame["proprio"], frame["instruction"], frame["family"], ids):
        obs = Observation(decode_frame(image), np.asarray(proprio, dtype=np.float32), {},
                          None if depth is None else decode_depth(depth))
        if episode_id is None or pd.isna(episode_id):
            decisions.append(policy.act(obs, instruction, family))
            continue
        if episode_id not in episodes:
            episodes[episode_id] = policy.episode(family)
            while len(episodes) > EPISODES_HELD:
                episodes.popitem(last=False)
        episodes.move_to_end(episode_id)
        decisions.append(episodes[episode_id](obs, instruction))
    return pd.DataFrame({"action": [d.action.astype(np.float64).tolist() for d in decisions],
                         "uncertainty": [d.uncertainty for d in decisions]})


set_model(PolicyModel())
