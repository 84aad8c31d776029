"""The policy as an MLflow pyfunc model ("models from code"), so the registry holds a loadable,
servable model: this file is logged with the checkpoint as its artifact."""

from __future__ import annotations

from pathlib import Path

import mlflow.pyfunc
import numpy as np
import pandas as pd
from mlflow.models import set_model

MODEL_CODE = __file__


class PolicyModel(mlflow.pyfunc.PythonModel):
    """Input: a DataFrame with `image` (a frame's bytes as the warehouse stores them: schemas.frames),
    `depth` (its depth map's bytes; RGB-D models only), `proprio` (list of floats), `instruction`
    (str), `family` (robosuite, metaworld, navigation).
    Output: a DataFrame with `action` (list of floats: continuous components, or [index]) and
    `uncertainty` (entropy or log det Sigma)."""

    def load_context(self, context) -> None:
        from policies.policy import Policy

        self.policy = Policy.load(Path(context.artifacts["checkpoint"]))

    def predict(self, context, model_input: pd.DataFrame, params: dict | None = None) -> pd.DataFrame:
        return predict_frame(self.policy, model_input)


def predict_frame(policy, frame: pd.DataFrame) -> pd.DataFrame:
    from envs.observation import Observation
    from schemas.frames import decode_depth, decode_frame

    depths = frame["depth"] if "depth" in frame else [None] * len(frame)
    decisions = [
        policy.act(Observation(decode_frame(image), np.asarray(proprio, dtype=np.float32), {},
                               None if depth is None else decode_depth(depth)), instruction, family)
        for image, depth, proprio, instruction, family in zip(frame["image"], depths, frame["proprio"],
                                                              frame["instruction"], frame["family"])
    ]
    return pd.DataFrame({"action": [d.action.astype(np.float64).tolist() for d in decisions],
                         "uncertainty": [d.uncertainty for d in decisions]})


set_model(PolicyModel())
