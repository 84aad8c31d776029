"""Simulator adapters, scripted experts, the task suite, rollouts and the worker pool they run in.

MuJoCo picks its GL backend when first imported: offscreen EGL unless the caller chose (MUJOCO_GL=osmesa).
Set here, once, before any module of this package can import mujoco, in every process that imports it."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
