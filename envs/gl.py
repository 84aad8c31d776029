"""Several environments render in one worker process, each through its own GL context, and
MuJoCo draws into whichever context is current and reads back whichever buffer is selected:
each adapter selects its own before it renders (or frees GL objects)."""

from __future__ import annotations

import mujoco


def select_offscreen(gl_context, mjr_context: mujoco.MjrContext) -> None:
    """Make `gl_context` current and its offscreen buffer the one drawn and read, whatever another
    environment's renderer left selected (frames would otherwise land there: wrong or black)."""
    gl_context.make_current()
    mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, mjr_context)
