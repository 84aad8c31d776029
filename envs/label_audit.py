"""`sim2act labels`: what the expert's labels on an explorer's states say, and why (DAgger, issue 9
item 5). An iteration's labelled episodes are replayed state by state through a fresh noiseless
expert, as explore's labeller followed them (`stages/explore._labeller`):

1. select the campaign's iteration's episodes whose explorer matches (the champion's by default)
   and whose steps carry expert labels; robosuite's only (a MetaWorld observation keeps the previous
   frame's positions, which its stored state does not restore): the others are counted and named;
2. reset each episode's environment as exploring reset it (without a camera here: the expert reads
   no pixels) and restore its steps' states in order (`RobosuiteEnv.observe_state`), asking the
   expert at each;
3. check every replayed label against the stored one (`mismatched`: 0 means the replay is faithful,
   and the counts below are the labeller's own);
4. count per task: the labels that close the gripper, the expert's phase at each step, the steps
   with the hand at the grasp point (`AT_GRASP`) or near it (twice that), and how far the expert
   would turn the wrist there, the way it chose (it calls a grasp only within `ALIGNED`).

What it found first: the hard-mix champion's 8,280 nut and stack steps of iteration 1 were labelled
"open" at every step, because its hand was at a grasp point on 12 of them (docs/results.md).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from envs.experts import AT_GRASP, expert_phase, grip_turn, hand_to_grasp
from schemas.errors import Sim2ActError
from warehouse.catalog import Catalog

REPLAYABLE_FAMILIES = ("robosuite",)


class LabelAuditError(Sim2ActError, ValueError):
    """`sim2act labels` refused before replaying anything; its message is one line."""


# How far a replayed label may lie from the stored one and still be it: a restored state can differ from the
# explored one by rounding (a takeover episode's label once by 4e-17), never by a label's worth.
SAME_LABEL = 1e-6


@dataclass
class TaskLabels:
    task_id: str
    episodes: int = 0
    steps: int = 0
    closed: int = 0  # replayed labels that close the gripper
    mismatched: int = 0  # steps whose replayed label differs from the stored one by more than SAME_LABEL (0: faithful)
    phases: Counter = field(default_factory=Counter)  # the expert's phase after labelling each step
    at_grasp: int = 0  # steps with the hand within AT_GRASP of the grasp point
    near_grasp: int = 0  # ... within twice that
    misturn_at_grasp: list[float] = field(default_factory=list)  # radians the expert would turn the wrist there


@dataclass
class LabelAudit:
    campaign: str
    iteration: int
    explorer: str  # the SQL LIKE pattern the episodes' explorer matched
    tasks: list[TaskLabels]
    skipped: Counter  # labelled episodes of families a replay cannot label, per family


def labelled_episodes(catalog: Catalog, iteration: int, explorer: str) -> list[tuple[str, str, str, str]]:
    """(campaign, episode_id, task_id, family) of the iteration's episodes by `explorer` whose steps carry
    expert labels."""
    return catalog.query(
        "SELECT e.campaign, e.episode_id, e.task_id, t.family FROM episodes e JOIN task_families t "
        "USING (campaign, task_id) WHERE e.iteration = ? AND e.explorer LIKE ? AND e.episode_id IN "
        "(SELECT DISTINCT episode_id FROM steps WHERE expert_action IS NOT NULL) ORDER BY e.task_id, e.episode_id",
        [iteration, explorer])


def audit_labels(catalog: Catalog, iteration: int, explorer: str = "policy%", campaign: str | None = None,
                 progress: Callable[[int, int], None] = lambda done, total: None) -> LabelAudit:
    """Replay the labelled episodes of `iteration` by `explorer` (steps in the module docstring).

    Args:
        catalog: the workspace's catalog (read only).
        iteration: the campaign iteration whose episodes are replayed.
        explorer: SQL LIKE pattern on `episodes.explorer` ("policy%": the champion's; "expert").
        campaign: whose episodes; None: the workspace's one campaign with such episodes.
        progress: called with (0, episodes in all) before the first episode, then after each.

    Returns:
        A LabelAudit, one TaskLabels per task, in task order.

    Raises:
        LabelAuditError: no labelled episode of a replayable family matches, or several campaigns do
            and none was named.
    """
    from envs.registry import make_expert
    from envs.replay import load_episode
    from envs.rollout import worker_env

    found = labelled_episodes(catalog, iteration, explorer)
    campaigns = sorted({row[0] for row in found})
    if campaign is None and len(campaigns) > 1:
        raise LabelAuditError(f"labels: iteration {iteration} holds labelled episodes of campaigns "
                              f"{', '.join(campaigns)}; expected one named (--campaign)")
    found = [row[1:] for row in found if campaign is None or row[0] == campaign]
    skipped = Counter(family for _, _, family in found if family not in REPLAYABLE_FAMILIES)
    episodes = [(episode_id, task_id) for episode_id, task_id, family in found if family in REPLAYABLE_FAMILIES]
    if not episodes:
        elsewhere = f" ({sum(skipped.values())} of {', '.join(skipped)}, which a replay cannot label)" if skipped else ""
        of = f" of campaign {campaign!r}" if campaign else ""
        raise LabelAuditError(
            f"labels: expected labelled {'/'.join(REPLAYABLE_FAMILIES)} episodes{of} of iteration {iteration} by an "
            f"explorer like {explorer!r}, got none{elsewhere}; on the same workspace, `sim2act sql "
            f"\"SELECT campaign, iteration, explorer, count(*) FROM episodes GROUP BY ALL ORDER BY ALL\"` lists what there is")
    stored: dict[str, list] = {}  # every episode's labels in step order, read in one pass over the steps
    for episode_id, label in catalog.query(
            "SELECT episode_id, expert_action FROM steps WHERE list_contains(?, episode_id) ORDER BY episode_id, step",
            [[episode_id for episode_id, _ in episodes]]):
        stored.setdefault(episode_id, []).append(label)
    tasks: dict[str, TaskLabels] = {}
    progress(0, len(episodes))
    for done, (episode_id, task_id) in enumerate(episodes, 1):
        episode = load_episode(catalog, episode_id)
        env = worker_env(episode.task, None)
        env.reset(episode.task, episode.seed, episode.randomisation)
        act = make_expert(episode.task, 0.0, np.random.default_rng(0))  # noiseless: its rng is never drawn
        expert = getattr(act, "__self__", None)
        row = tasks.setdefault(task_id, TaskLabels(task_id))
        row.episodes += 1
        for step, (state, label) in enumerate(zip(episode.states, stored[episode_id])):
            obs = env.observe_state(state, after_step=step > 0)
            replayed = np.asarray(act(obs), dtype=np.float32)
            row.steps += 1
            row.closed += int(replayed[-1] > 0)
            row.mismatched += int(label is None or not np.allclose(replayed, np.asarray(label, dtype=np.float32),
                                                                   rtol=0, atol=SAME_LABEL))
            row.phases[expert_phase(expert)[1]] += 1
            seen = obs.privileged
            distance = hand_to_grasp(seen)
            if distance is not None:
                row.near_grasp += int(distance < 2 * AT_GRASP)
                if distance < AT_GRASP:
                    row.at_grasp += 1
                    row.misturn_at_grasp.append(_wrist_turn(expert, seen))
        progress(done, len(episodes))
    return LabelAudit(campaign=campaign or (campaigns[0] if campaigns else ""), iteration=iteration, explorer=explorer,
                      tasks=list(tasks.values()), skipped=skipped)


def _wrist_turn(expert, seen: dict[str, np.ndarray]) -> float:
    """Radians the expert would turn the wrist at this state: the way it chose where it is aiming
    (approach, descend: what it compares with ALIGNED), else the shorter way to the grip axis."""
    aim, wrist = getattr(expert, "aim", None), getattr(expert, "wrist", None)
    if aim is not None and wrist is not None:
        return abs(aim - wrist)
    axis, wanted = seen["finger_axis"], seen["grip_axis"]
    return abs(grip_turn(wanted, float(np.arctan2(axis[1], axis[0])))) if wanted[:2].any() else 0.0


def _total(tasks: list[TaskLabels]) -> TaskLabels:
    """Every task's counts summed, as the row "all"."""
    total = TaskLabels("all")
    for row in tasks:
        for name in ("episodes", "steps", "closed", "mismatched", "at_grasp", "near_grasp"):
            setattr(total, name, getattr(total, name) + getattr(row, name))
        total.phases.update(row.phases)
        total.misturn_at_grasp += row.misturn_at_grasp
    return total


def markdown(audit: LabelAudit) -> str:
    """The audit as a table, a row per task and a total."""
    phases = sorted({phase for row in audit.tasks for phase in row.phases})
    lines = [
        f"Campaign `{audit.campaign}`, iteration {audit.iteration}, episodes by an explorer like `{audit.explorer}`, "
        "replayed through the noiseless expert:", "",
        "| task | episodes | steps | labels closing | replayed ≠ stored | at grasp point | within 2× | "
        "wrist turn the expert wants there (median rad) | " + " | ".join(f"phase {p}" for p in phases) + " |",
        "|---|" + "---|" * (7 + len(phases)),
    ]
    total = _total(audit.tasks)
    for row in [*audit.tasks, total]:
        misturn = f"{np.median(row.misturn_at_grasp):.2f}" if row.misturn_at_grasp else "-"
        name = f"**{row.task_id}**" if row is total else row.task_id
        lines.append(f"| {name} | {row.episodes} | {row.steps:,} | {row.closed:,} | {row.mismatched:,} | "
                     f"{row.at_grasp:,} | {row.near_grasp:,} | {misturn} | "
                     + " | ".join(f"{row.phases.get(p, 0):,}" for p in phases) + " |")
    if audit.skipped:
        lines += ["", "Not replayed (a replay cannot label them): "
                  + ", ".join(f"{n} {family} episode(s)" for family, n in sorted(audit.skipped.items())) + "."]
    return "\n".join(lines)
