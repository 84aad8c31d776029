"""The docs table of each task's scripted expert (measured by envs.expert_check) made from the record
(schemas.experts) that decides which tasks campaigns may use (target: >= 90% per task)."""

from __future__ import annotations

from envs.expert_check import EPISODES
from schemas.experts import TARGET, ExpertTable


def markdown(table: ExpertTable, suite_order: list[str], record: str) -> str:
    rows = sorted(table.rows.values(), key=lambda r: (r.task_id not in suite_order,
                                                       suite_order.index(r.task_id) if r.task_id in suite_order else 0,
                                                       r.task_id))
    below = [r for r in rows if r.below_target]
    made_by = sorted({(r.command, r.measured_on, r.noise, r.randomised) for r in rows})
    lines = ["# Scripted expert success per task", ""]
    for command, day, noise, randomised in made_by:
        conditions = "the default domain randomisation" if randomised else "no domain randomisation"
        lines.append(f"- `{command}` on {day}: expert action noise σ={noise}, {conditions}")
    lines += [
        "",
        f"Episode seeds are derived per task. Target: ≥{TARGET:.0%}; {len(below)} of {len(rows)} tasks are below "
        "it, flagged here, and left out of campaigns unless a config sets `tasks.weak_experts: keep`. "
        f"The record behind this page is `{record}`. A campaign whose randomisation an expert can feel (object "
        "masses, sizes or frictions away from the default, or none at all) measures its tasks' experts again under "
        f"its own, {EPISODES} episodes each, once per workspace, and leaves out those below target in one line before "
        "exploring (envs/expert_check.py).",
        "",
        "| task | family | split | success | episodes | mean length | flag |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        flag = "below target" if r.below_target else ""
        lines.append(f"| {r.task_id} | {r.family} | {r.split} | {r.success_rate:.0%} | {r.episodes} | "
                     f"{r.mean_length:.0f} | {flag} |")
    return "\n".join(lines) + "\n"
