"""`sim2act shadow`: a model's evaluation episodes with the noiseless scripted expert shadowing it.
The policy acts; at every state it reaches the expert is asked what it would do there (as explore's
DAgger labeller is), and never acts. Where the two part names the failure: the policy closing its
gripper a few centimetres short of the grasp point, moving at a fraction of the expert's speed,
turning away. A success rate says that a task fails; this says how (issue 9 item 5).

1. the caller runs each episode through `shadow_episode` (stages.evaluate.shadow_unit: the
   evaluation's own agent, seeds, render and randomisation, so the episodes are `sim2act eval`'s);
2. per step: the policy's action and the expert's on the same observation, the expert's phase
   after answering (how far the policy's states got, in the expert's eyes), and where the hand is;
3. per task (`CaseShadow.add`): agreement (cosine of the translations, over the episode and before the
   policy first closes its gripper; the same action on discrete families), the policy's speed against the expert's, the gripper decisions the expert would not
   take (closing where it opens: a grasp tried short; opening where it holds: a drop), the hand's
   distance to the grasp point when the policy first closes, and the furthest expert phase reached;
4. per spec (`placement_markdown`): whether the policy's first move follows where the object is. Each
   episode starts from a placement the model never trained on (or, `sim2act shadow --placements trained`,
   from one its training episodes started at), and the expert's first move points at the object; across a
   spec's episodes, a policy that localises moves as the expert varies (correlation near 1), one that
   memorised its training placements moves the same way wherever the object is.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from envs.experts import expert_phase, hand_to_grasp
from envs.observation import DISCRETE_FAMILIES, Observation
from envs.rollout import rollout
from schemas.tasks import TaskRecord

Act = Callable[[Observation], np.ndarray]
MOVING = 0.05  # a translation smaller than this (of the unit action) is "standing still": no direction to compare
GRIP = 6  # the gripper's component of a continuous action (envs.observation.ACTION_COMPONENTS): > 0 closes


@dataclass
class EpisodeShadow:
    success: bool
    steps: int
    cosines: list[float]  # per step where both move: cos(policy translation, expert translation)
    cosines_before_close: list[float]  # ... those before the policy first closes the gripper (its approach)
    same_action: int  # discrete families: steps where the policy took the expert's action
    policy_speed: float  # summed |translation| of the policy's actions
    expert_speed: float  # ... and of the expert's on the same states
    closes_short: int  # steps the policy closes the gripper where the expert keeps it open
    opens_early: int  # steps the policy opens it where the expert keeps it closed
    first_close_cm: float | None  # the hand's distance to the grasp point at the policy's first close
    furthest_phase: str  # the expert's furthest phase over the episode ("-": an expert without phases)
    first_moves: tuple[list[float], list[float]] | None = None  # the policy's and the expert's first translation


def shadow_episode(env, task: TaskRecord, seed: int, act: Act, expert: Act, randomisation=None,
                   placements: str = "benchmark", steps: int | None = None) -> EpisodeShadow:
    """One episode of `act` with `expert` (a fresh noiseless expert, or its bound `act`) asked at every state;
    `placements` and `steps` as `rollout`'s (evaluate.metaworld_placements, evaluate.max_steps)."""
    distances: list[float | None] = []
    phases: list[tuple[int, str]] = []
    owner = getattr(expert, "__self__", expert)

    def policy(obs: Observation) -> np.ndarray:
        distances.append(hand_to_grasp(obs.privileged))
        return act(obs)

    def shadowing(obs: Observation) -> np.ndarray:
        action = expert(obs)
        phases.append(expert_phase(owner))
        return action

    rows, _, success = rollout(env, task, seed, policy, randomisation, label=shadowing, steps=steps,
                                placements=placements)
    taken = np.asarray([r["action"] for r in rows], dtype=np.float64)
    wanted = np.asarray([r["expert_action"] for r in rows], dtype=np.float64)
    discrete = task.family in DISCRETE_FAMILIES
    cosines, before, closes_short, opens_early, first_close = [], [], 0, 0, None
    policy_speed = expert_speed = 0.0
    if not discrete:
        moved, asked = taken[:, :3], wanted[:, :3]
        norms, asked_norms = np.linalg.norm(moved, axis=1), np.linalg.norm(asked, axis=1)
        policy_speed, expert_speed = float(norms.sum()), float(asked_norms.sum())
        both = (norms > MOVING) & (asked_norms > MOVING)
        cosine = (moved * asked).sum(1) / np.maximum(norms * asked_norms, 1e-12)
        closes, holds = taken[:, GRIP] > 0, wanted[:, GRIP] > 0
        closes_short, opens_early = int((closes & ~holds).sum()), int((~closes & holds).sum())
        first = int(np.argmax(closes)) if closes.any() else None
        cosines = cosine[both].tolist()
        before = cosine[both & (np.arange(len(rows)) < (len(rows) if first is None else first))].tolist()
        if first is not None and distances[first] is not None:
            first_close = 100.0 * distances[first]
    furthest = max(phases)[1] if phases else "-"
    return EpisodeShadow(
        success=bool(success), steps=len(rows), cosines=cosines, cosines_before_close=before,
        same_action=int((taken[:, 0] == wanted[:, 0]).sum()) if discrete else 0,
        policy_speed=policy_speed, expert_speed=expert_speed, closes_short=closes_short, opens_early=opens_early,
        first_close_cm=first_close, furthest_phase=furthest,
        first_moves=None if discrete or not rows else (taken[0, :3].tolist(), wanted[0, :3].tolist()),
    )


@dataclass
class CaseShadow:
    """One evaluation case's episodes, summed."""

    task_id: str
    split: str
    discrete: bool
    episodes: int = 0
    successes: int = 0
    steps: int = 0
    cosines: list[float] = field(default_factory=list)
    cosines_before_close: list[float] = field(default_factory=list)
    same_action: int = 0
    policy_speed: float = 0.0
    expert_speed: float = 0.0
    closes_short: int = 0
    opens_early: int = 0
    first_close_cm: list[float] = field(default_factory=list)
    furthest: Counter = field(default_factory=Counter)  # the expert's furthest phase -> episodes
    spec: str = ""  # the task's spec: the placement table pools a spec's colours ("": the task alone)
    first_moves: list[tuple[list[float], list[float]]] = field(default_factory=list)  # per episode

    def add(self, episode: EpisodeShadow) -> CaseShadow:
        self.episodes += 1
        self.successes += int(episode.success)
        self.steps += episode.steps
        self.cosines += episode.cosines
        self.cosines_before_close += episode.cosines_before_close
        self.same_action += episode.same_action
        self.policy_speed += episode.policy_speed
        self.expert_speed += episode.expert_speed
        self.closes_short += episode.closes_short
        self.opens_early += episode.opens_early
        if episode.first_close_cm is not None:
            self.first_close_cm.append(episode.first_close_cm)
        self.furthest[episode.furthest_phase] += 1
        if episode.first_moves is not None:
            self.first_moves.append(episode.first_moves)
        return self


def markdown(cases: list[CaseShadow], label: str) -> str:
    """A row per evaluation case: where the policy and the shadowing expert part."""
    lines = [
        f"{label}, its evaluation episodes shadowed by the noiseless expert (asked at every state, never acting):", "",
        "| task | split | success | steps | agrees with the expert | ... before its first close | speed, policy / "
        "expert | closes where the expert opens | opens where it holds | hand to grasp point at first close (median "
        "cm) | furthest expert phase (episodes) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for case in cases:
        if case.discrete:
            agrees, speed = f"{case.same_action / max(case.steps, 1):.0%} same action", "-"
            approach = closes = opens = first = "-"
        else:
            agrees = f"cos {np.mean(case.cosines):.2f}" if case.cosines else "-"
            approach = f"cos {np.mean(case.cosines_before_close):.2f}" if case.cosines_before_close else "-"
            speed = f"{case.policy_speed / case.expert_speed:.2f}" if case.expert_speed else "-"
            closes, opens = f"{case.closes_short:,}", f"{case.opens_early:,}"
            first = f"{np.median(case.first_close_cm):.1f}" if case.first_close_cm else "-"
        phases = ", ".join(f"{name} {n}" for name, n in case.furthest.most_common())
        lines.append(f"| {case.task_id} | {case.split} | {case.successes}/{case.episodes} | {case.steps:,} | {agrees} | "
                     f"{approach} | {speed} | {closes} | {opens} | {first} | {phases} |")
    return "\n".join(lines)


STILL = 0.02  # an expert first move varying less than this across placements (sd, unit action) has nothing to follow


def placement_markdown(cases: list[CaseShadow], least: int = 3, trained: bool = False) -> str:
    """A row per spec (its colours and splits pooled) with at least `least` episodes: across their first
    states, the correlation of the policy's first hand motion with the expert's per axis, and each one's
    spread. `trained`: the episodes started where the model's training episodes did (the caption says so).
    "" when no spec has enough episodes of a continuous family."""
    pooled: dict[str, list[tuple[list[float], list[float]]]] = {}
    for case in cases:
        pooled.setdefault(case.spec or case.task_id, []).extend(case.first_moves)
    rows = []
    for spec, moves in pooled.items():
        if len(moves) < least:
            continue
        policy, expert = (np.asarray([m[i] for m in moves], dtype=np.float64) for i in (0, 1))
        spread_p, spread_e = policy.std(0), expert.std(0)
        r = ["-" if spread_e[a] < STILL else "policy constant" if spread_p[a] < 1e-9
             else f"{np.corrcoef(policy[:, a], expert[:, a])[0, 1]:+.2f}" for a in range(3)]
        rows.append(f"| {spec} | {len(moves)} | " + " | ".join(r) + " | "
                    + ", ".join(f"{spread_p[a]:.2f} / {spread_e[a]:.2f}" for a in range(3)) + " |")
    if not rows:
        return ""
    return "\n".join([
        "Does the first move follow the placement? Each episode starts from "
        + ("the object placement one of the model's training episodes started from" if trained else
           "an object placement the model never trained on")
        + "; across a spec's episodes, the correlation of the policy's first hand motion with the "
        f"expert's per axis (-: the expert's varies by less than {STILL}), and their spreads. Near 1 the policy "
        "localises the object; near 0, or a policy that hardly varies, it moves as it learned to wherever the object is:", "",
        "| spec | episodes | r, x | r, y | r, z | sd of the first move, policy / expert (x, y, z) |",
        "|---|---|---|---|---|---|", *rows])
