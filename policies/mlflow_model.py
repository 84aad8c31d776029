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
    `proprio` (list of floats), `instruction` (str)."""

    def load_context(self, context) -> None:
        from policies.policy import Policy

        self.policy = Policy.load(Path(context.artifacts["checkpoint"]))

    def predict(self, context, model_input: pd.DataFrame, params: dict | None = None) -> np.ndarray:
        from policies.language import encode
        from schemas.frames import decode_frame

        embeddings = encode(self.policy.language_encoder, list(model_input["instruction"]))
        return np.stack(
            [
                self.policy.act(decode_frame(image), np.asarray(proprio, dtype=np.float32), embedding)
                for image, proprio, embedding in zip(model_input["image"], model_input["proprio"], embeddings)
            ]
        )


set_model(PolicyModel())
