"""`sim2act bench envs`: environment steps per second, one layer at a time.

For each family, side by side in one run: the raw MuJoCo physics of one control step
(`mj_step` times the substeps the simulator takes per action), the simulator's own env step
without a camera, our adapter without a camera, and our adapter rendering 84x84 frames (for
robosuite and MetaWorld also with their visual meshes decimated, `render.mesh_detail`, and MetaWorld with its
colliding meshes drawn decimated too, `render.decimate_colliding`). Ratios to the raw step
show what each wrapper layer costs; the render share of an adapter step is 1 - (with frames / without). For
robosuite, the adapter's layers without a camera and with decimated meshes again with robosuite's own arm
controller at every substep instead of the fused substeps (envs/robosuite_control.py: the same states bit for
bit), each measured in turns with its fused counterpart. Every family runs in a fresh
process, one after the other, so GL contexts and core use do not mix.
"""

from __future__ import annotations

import datetime
import time
from collections.abc import Callable

import mujoco
import numpy as np
from pydantic import BaseModel

from bench.tables import table
from envs.pool import run_in_pool
from envs.robosuite_control import controller_path
from schemas.config import RenderConfig, TasksConfig

# one representative task per family
BENCH_SPECS = {"robosuite": "lift", "metaworld": "mw-pick-place", "navigation": "nav-room-sequence"}
MESH_DETAIL = 0.1  # the decimated layer's render.mesh_detail
LAYERS = ("raw mj_step", "simulator env.step", "sim2act adapter", "sim2act adapter + 84px render",
          f"sim2act adapter + 84px render, visual meshes at {MESH_DETAIL:g}",
          f"sim2act adapter + 84px render, meshes at {MESH_DETAIL:g}, colliding ones too")
MESH_DETAIL_FAMILIES = {"robosuite", "metaworld"}  # the adapters that apply render.mesh_detail
# the adapters whose cameras draw colliding meshes (robosuite hides its collision geoms: nothing it draws changes)
COLLIDING_FAMILIES = {"metaworld"}
STOCK_CONTROL_LAYERS = ("sim2act adapter, robosuite's controller",
                        f"sim2act adapter + 84px render, visual meshes at {MESH_DETAIL:g}, robosuite's controller")
EPISODE_STEPS = 100  # reset this often, outside the timed calls


class BenchCase(BaseModel):
    family: str
    steps: int
    image_size: int = 84


class BenchRow(BaseModel):
    family: str
    env: str
    layer: str
    steps_per_s: float
    relative_to_raw: float


Layer = tuple[Callable[[int], None], Callable[[], None]]  # (step i, reset)


def _rates(layers: dict[str, Layer], steps: int) -> dict[str, float]:
    """Control steps per second of each layer, resetting every EPISODE_STEPS steps off the clock.
    Several layers are measured in turns of EPISODE_STEPS, the order reversed each turn, so that
    a drift in the machine's speed falls on all of them alike."""
    elapsed, done = dict.fromkeys(layers, 0.0), 0
    while done < steps:
        chunk = min(EPISODE_STEPS, steps - done)
        turn = list(layers.items())
        for name, (step, reset) in turn if (done // EPISODE_STEPS) % 2 == 0 else reversed(turn):
            reset()
            started = time.perf_counter()
            for i in range(chunk):
                step(i)
            elapsed[name] += time.perf_counter() - started
        done += chunk
    return {name: steps / seconds for name, seconds in elapsed.items()}


def _rate(step: Callable[[int], None], reset: Callable[[], None], steps: int) -> float:
    return _rates({"": (step, reset)}, steps)[""]


def _make_stock(family: str, env_name: str, render: RenderConfig | None):
    """An environment with robosuite's own controller at every substep (read when it is made)."""
    from envs.registry import make_env

    with controller_path(stock=True):
        return make_env(family, env_name, render)


def measure_family(case: BenchCase) -> list[BenchRow]:
    """Worker: every layer of one family, the same actions for each; for robosuite, each adapter
    layer interleaved with the same layer through robosuite's own controller."""
    from envs.registry import make_env
    from envs.suite import generate_tasks

    task = generate_tasks(TasksConfig(specs=[BENCH_SPECS[case.family]]), seed=0)[0]
    rng = np.random.default_rng(0)
    if case.family == "navigation":
        actions = rng.integers(0, 4, size=(EPISODE_STEPS, 1)).astype(np.float32)
    else:
        actions = rng.uniform(-1, 1, size=(EPISODE_STEPS, 7)).astype(np.float32)
    stock_too = case.family == "robosuite"

    def layer(env) -> Layer:
        return (lambda i: env.step(actions[i])), (lambda: env.reset(task, seed=0))

    def with_stock(name: str, env, stock_name: str, render: RenderConfig | None) -> dict[str, float]:
        """`env`'s layer, and interleaved with it the same through robosuite's controller."""
        if not stock_too:
            return _rates({name: layer(env)}, case.steps)
        stock = _make_stock(case.family, task.env_name, render)
        try:
            return _rates({name: layer(env), stock_name: layer(stock)}, case.steps)
        finally:
            stock.close()

    plain = make_env(case.family, task.env_name, None)
    model, data, substeps = plain.physics()
    rates: dict[str, float] = {}

    def reset_plain() -> None:
        plain.reset(task, seed=0)

    rates[LAYERS[0]] = _rate(lambda i: mujoco.mj_step(model, data, nstep=substeps), reset_plain, case.steps)
    if hasattr(plain, "native_step"):  # navigation is ours all the way down
        rates[LAYERS[1]] = _rate(lambda i: plain.native_step(actions[i]), reset_plain, case.steps)
    rates.update(with_stock(LAYERS[2], plain, STOCK_CONTROL_LAYERS[0], None))
    plain.close()
    rendered = make_env(case.family, task.env_name, RenderConfig(image_size=case.image_size))
    rates[LAYERS[3]] = _rate(lambda i: rendered.step(actions[i]), lambda: rendered.reset(task, seed=0), case.steps)
    rendered.close()
    if case.family in MESH_DETAIL_FAMILIES:
        render = RenderConfig(image_size=case.image_size, mesh_detail=MESH_DETAIL)
        coarse = make_env(case.family, task.env_name, render)
        rates.update(with_stock(LAYERS[4], coarse, STOCK_CONTROL_LAYERS[1], render))
        coarse.close()
    if case.family in COLLIDING_FAMILIES:
        coarser = make_env(case.family, task.env_name,
                           RenderConfig(image_size=case.image_size, mesh_detail=MESH_DETAIL, decimate_colliding=True))
        rates[LAYERS[5]] = _rate(lambda i: coarser.step(actions[i]), lambda: coarser.reset(task, seed=0), case.steps)
        coarser.close()
    raw = rates[LAYERS[0]]
    return [BenchRow(family=case.family, env=task.env_name, layer=layer, steps_per_s=rate, relative_to_raw=rate / raw)
            for layer, rate in rates.items()]


def bench_envs(families: list[str], steps: int) -> list[BenchRow]:
    rows = []
    for family in families:  # one fresh process per family, one at a time
        for _, family_rows, _ in run_in_pool(measure_family, [BenchCase(family=family, steps=steps)], workers=1):
            rows.extend(family_rows)
    return rows


def render_shares(rows: list[BenchRow]) -> list[list[str]]:
    """Per family: 1 - (steps/s with frames) / (steps/s without), at full detail, decimated, and with the
    colliding meshes decimated too."""
    shares = []
    for family in dict.fromkeys(r.family for r in rows):
        rate = {r.layer: r.steps_per_s for r in rows if r.family == family}
        share = [f"{1 - rate[layer] / rate[LAYERS[2]]:.0%}" if layer in rate else "—" for layer in LAYERS[3:6]]
        shares.append([family, *share])
    return shares


def markdown(rows: list[BenchRow], command: str) -> str:
    lines = [
        "# Environment steps per second, layer by layer",
        "",
        f"Made by `{command}` on {datetime.date.today().isoformat()}: one process, one core per family, "
        "random actions, resets off the clock. A step is one control step (one action).",
        "",
        *table(["family", "env", "layer", "steps/s", "× raw"],
               [[r.family, r.env, r.layer, f"{r.steps_per_s:,.0f}", f"{r.relative_to_raw:.3f}"] for r in rows]),
        "",
        "The render's share of an adapter step (target ≤ 30%, issue 11):",
        "",
        *table(["family", "render share", f"with visual meshes at {MESH_DETAIL:g}", "and colliding ones too"],
               render_shares(rows)),
    ]
    return "\n".join(lines) + "\n"

