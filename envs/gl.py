"""Several environments render in one worker process, each through its own GL context, and
MuJoCo draws into whichever context is current and reads back whichever buffer is selected:
each adapter selects its own before it renders (or frees GL objects)."""

from __future__ import annotations

import mujoco


def size_offscreen(model: mujoco.MjModel, render) -> None:
    """A model's offscreen settings for `render` (a RenderConfig), set before its renderer's context is
    made: a framebuffer the size of the image, the multisamples asked for, and no shadow map when
    shadows are off. MuJoCo allocates the map (shadowsize²: 4096², 64 MiB, in MetaWorld's models and by
    MuJoCo's default in robosuite's) whether or not it draws shadows; frames bit for bit the same
    without it (tests/envs)."""
    model.vis.quality.offsamples = render.multisamples
    model.vis.global_.offwidth = render.image_size
    model.vis.global_.offheight = render.image_size
    if not render.shadows:
        model.vis.quality.shadowsize = 0


def select_offscreen(gl_context, mjr_context: mujoco.MjrContext) -> None:
    """Make `gl_context` current and its offscreen buffer the one drawn and read, whatever another
    environment's renderer left selected (frames would otherwise land there: wrong or black)."""
    gl_context.make_current()
    mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, mjr_context)
