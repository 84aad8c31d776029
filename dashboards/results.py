"""The results table (`sim2act report`): a campaign's success per iteration beside its
baselines on the same evaluation cases and seeds, its dataset per iteration, and the compute
each number took — Markdown, from the warehouse alone."""

from __future__ import annotations

import datetime
import json
import os
import platform
import time
from collections import Counter
from pathlib import Path

from dashboards.protocol import ablations, climbs, differing_settings, loop_groups, seed_groups
from dashboards.report import evaluations_by_iteration
from schemas.tables import CURRENT_ITERATIONS, CURRENT_TASK_FAMILIES
from schemas.tasks import CAMPAIGN_SUITE, UNSEEN_PARAPHRASE
from schemas.wordings import HELD_OUT_WORDING
from stages.adapt import (STAGE as ADAPT_STAGE, SUITE as ADAPT_SUITE, AdaptPoint, AdaptResult, adapt_results,
                          episodes_to_reach, points_of_family, pooled, pooled_score)
from stages.baselines import EXPERT, STAGE as BASELINES_STAGE, agents_in_training, all_plans, campaign_plans
from stages.evaluate import SPLITS, GroupSuccess, TaskEvaluation, evaluation_cases, group_success, read_evaluations
from stages.generate_tasks import STAGE as TASKS_STAGE
from warehouse.catalog import Catalog
from warehouse.tasks import tasks_of_unit

SPLIT_COLUMNS = ("seen", "unseen", UNSEEN_PARAPHRASE)


def split_columns(by_iteration: dict[int, list[GroupSuccess]]) -> tuple[str, ...]:
    """The split tables' columns: seen, unseen and the held-out paraphrase always, and the held-out wordings
    where the campaign evaluated them (evaluate.held_out_wordings: the policy's test alone, no baseline meets it)."""
    held_out = any(g.group == HELD_OUT_WORDING for groups in by_iteration.values() for g in groups)
    return SPLIT_COLUMNS + ((HELD_OUT_WORDING,) if held_out else ())
AGENT_NAMES = {EXPERT: "scripted expert, noiseless (ceiling)", "ppo": "PPO from scratch", "sac": "SAC from scratch"}


def running_seconds(spans: list[tuple[float, float]]) -> float:
    """The length of the union of the (start, end) spans: the seconds in which at least one was under way.
    A campaign stopped in the evening and resumed the next day was not running overnight; its elapsed time
    says it was."""
    total, current = 0.0, None
    for start, end in sorted(spans):
        if current is not None and start <= current[1]:
            current = (current[0], max(current[1], end))
            continue
        if current is not None:
            total += current[1] - current[0]
        current = (start, end)
    return total + (current[1] - current[0] if current is not None else 0.0)


def _cell(group: GroupSuccess | None) -> str:
    if group is None:
        return "–"
    return (f"{group.successes}/{group.episodes} = {group.success_rate:.0%} "
            f"({group.ci_low:.0%}–{group.ci_high:.0%})")


def _cells(groups: list[GroupSuccess], columns: list[str] | tuple[str, ...] = SPLIT_COLUMNS) -> list[str]:
    by_name = {g.group: g for g in groups}
    return [_cell(by_name.get(column)) for column in columns]


def _table(header: list[str], rows: list[list[object]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return lines + ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]


WIDE_TABLE_NAMES = 3  # families or specs side by side at most; more get a row each (the generalist has 63 specs)


def _split_table(title: str, by_iteration: dict[int, list[GroupSuccess]], names: list[str]) -> list[str]:
    """Success per iteration in every split of each family or spec `names` (groups "<name>/<split>"):
    a column per name and split for a few names, else a row per name and iteration."""
    splits = split_columns(by_iteration)
    if len(names) > WIDE_TABLE_NAMES:
        rows = [[name, iteration, *_cells(groups, [f"{name}/{split}" for split in splits])]
                for name in names for iteration, groups in sorted(by_iteration.items())]
        return ["", f"### {title}", "", *_table(["", "iteration", *[s.replace("_", " ") for s in splits]], rows)]
    header = ["iteration", *[f"{name}/{split}" for name in names for split in splits]]
    return ["", f"### {title}", "",
            *_table(header, [[iteration, *_cells(groups, header[1:])] for iteration, groups in sorted(by_iteration.items())])]


Baselines = dict[tuple[str, str | None, int, str], list[TaskEvaluation]]


def baseline_evaluations(catalog: Catalog, campaign: str) -> Baselines:
    """(agent, family, environment steps its training took, model key) -> its evaluations on the campaign's
    cases; the expert first, then by agent and family. Two trainings of one agent and family (another encoder
    layout, another replay size) are two entries, never pooled."""
    trained = {key: json.loads(summary) for key, summary in catalog.query(
        "SELECT unit_key, summary FROM stage_runs WHERE stage = ? AND campaign = ?", [BASELINES_STAGE, campaign])}
    rows = read_evaluations(catalog, "v.model_key",
                            "WHERE v.campaign = ? AND v.suite = ? AND list_contains(?, v.model_key) "
                            "ORDER BY v.task_id, v.split", [campaign, CAMPAIGN_SUITE, [EXPERT, *trained]])
    grouped: Baselines = {}
    for model_key, evaluation in rows:
        agent = trained.get(model_key, {"algorithm": EXPERT, "family": None, "steps_taken": 0})
        grouped.setdefault((agent["algorithm"], agent["family"], agent["steps_taken"], model_key), []).append(evaluation)
    order = list(AGENT_NAMES)
    return dict(sorted(grouped.items(), key=lambda item: (order.index(item[0][0]), item[0][1] or "", item[0][3])))


def _agent_name(agent: str, family: str | None, model_key: str, baselines: Baselines) -> str:
    """The row's agent: its name, and its model key where another training of the same agent and family sits beside it."""
    twins = sum(1 for a, f, _, _ in baselines if (a, f) == (agent, family))
    return AGENT_NAMES.get(agent, agent) + (f" [{model_key}]" if twins > 1 else "")


def _evaluating(evaluations: list[TaskEvaluation], cases: int) -> str:
    """A baseline read mid-evaluation says so: its pooled figures are the cases so far of `cases`."""
    met = len({(e.task_id, e.split, e.instruction) for e in evaluations})
    return f", evaluating: {met}/{cases} cases" if met < cases else ""


def family_baselines_markdown(by_iteration: dict[int, list[GroupSuccess]],
                              baselines: Baselines,
                              families: list[str], cases: Counter,
                              steps_through: dict[tuple[int, str], int]) -> list[str]:
    """Each family's rows side by side: Sim2Act per iteration, then every baseline evaluated on that
    family's cases (the expert's over all families, narrowed to it; an RL agent's are its family's).
    The claim "higher success on unseen tasks than RL from scratch" is read here, family by family:
    the pooled table above mixes a family where RL learns something with one where it learns nothing.
    `cases`: family -> the cases the last iteration's model met there; `steps_through`: (iteration,
    family) -> the environment steps its dataset explored on the family, which an RL agent's budget
    matches by default."""
    if not baselines:
        return []
    splits = split_columns(by_iteration)
    rows = []
    for family in families:
        columns = [f"{family}/{split}" for split in splits]
        rows += [[family, f"Sim2Act iteration {iteration}", f"{steps_through.get((iteration, family), 0):,}",
                  *_cells(groups, columns)] for iteration, groups in sorted(by_iteration.items())]
        for (agent, agent_family, steps, model_key), evaluations in baselines.items():
            met = [e for e in evaluations if e.family == family]
            if not met:  # an RL agent of another family
                continue
            rows.append([family, _agent_name(agent, agent_family, model_key, baselines) + _evaluating(met, cases[family]),
                         f"{steps:,}" if steps else "–", *_cells(group_success(met), columns)])
    header = ["family", "agent", "env steps (training data)", *[split.replace("_", " ") for split in splits]]
    return ["", "### Per family, against the baselines", "", *_table(header, rows)]


UNSEEN_KINDS = ("unseen colours", "unseen whole tasks")


def unseen_kinds(catalog: Catalog, campaign: str) -> dict[str, str]:
    """The campaign's unseen tasks -> their kind: a held-out colouring of a spec it trains on (a seen task of the
    same spec exists: "unseen colours"), or a spec it never trains on ("unseen whole tasks")."""
    tasks = catalog.query(f"SELECT task_id, spec, split FROM {CURRENT_TASK_FAMILIES} WHERE campaign = ?", [campaign])
    seen_specs = {spec for _, spec, split in tasks if split == "seen"}
    return {task_id: UNSEEN_KINDS[spec not in seen_specs] for task_id, spec, split in tasks if split == "unseen"}


def unseen_by_kind_markdown(evaluations: dict[int, list[TaskEvaluation]], baselines: Baselines,
                            kinds: dict[str, str], cases: Counter) -> list[str]:
    """The unseen split of each family cut in two, Sim2Act per iteration beside every baseline: a held-out
    colour of a trained spec asks the policy to read a word it knows in a new pairing; a whole task never
    trained on asks for a skill. Pooled together (the split tables), a family holding both hides which one
    its figure is. Only where some unseen task is a whole one (`kinds`: unseen_kinds); `cases` as
    family_baselines_markdown's."""
    if UNSEEN_KINDS[1] not in kinds.values():
        return []

    def unseen(met: list[TaskEvaluation]) -> list[TaskEvaluation]:
        # a case evaluated unseen whose task the campaign's tasks now hold as seen (a changed tasks.*) has no kind
        return [e for e in met if e.split == "unseen" and e.task_id in kinds]

    evaluated = {(e.family, e.task_id) for found in [*evaluations.values(), *baselines.values()] for e in unseen(found)}
    families = sorted({family for family, _ in evaluated})
    tasks = Counter((family, kinds[task_id]) for family, task_id in evaluated)

    def cells(met: list[TaskEvaluation]) -> list[str]:
        return _cells(group_success([e.model_copy(update={"split": kinds[e.task_id]}) for e in unseen(met)]),
                      UNSEEN_KINDS)

    rows = []
    for family in families:
        said = f"{family} ({tasks[family, UNSEEN_KINDS[0]]} + {tasks[family, UNSEEN_KINDS[1]]})"
        rows += [[said, f"Sim2Act iteration {iteration}", *cells([e for e in found if e.family == family])]
                 for iteration, found in sorted(evaluations.items())]
        for (agent, agent_family, _, model_key), found in baselines.items():
            met = [e for e in found if e.family == family]
            if met:
                rows.append([said, _agent_name(agent, agent_family, model_key, baselines)
                             + _evaluating(met, cases[family]), *cells(met)])
    return ["", "### Unseen, by kind, per family", "",
            "The unseen split cut in two: a seen spec's held-out colours, and whole tasks whose spec the campaign "
            "never trains on (the family column counts the unseen tasks of each kind).", "",
            *_table(["family (colours + whole)", "agent", *UNSEEN_KINDS], rows)]


def _utc(seconds: float | None) -> str:
    return "–" if seconds is None else datetime.datetime.fromtimestamp(
        seconds, datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")


def _run_started(holder: dict) -> float | None:
    """When the holding run started (epoch seconds): its `started`, or its `since` where a run of
    older code wrote only that (local time, this machine's zone)."""
    if isinstance(holder.get("started"), (int, float)):
        return float(holder["started"])
    try:
        return time.mktime(time.strptime(str(holder.get("since")), "%Y-%m-%d %H:%M:%S"))
    except ValueError:
        return None


def pending_baselines_markdown(catalog: Catalog, campaign: str, models: Path, holder: dict | None) -> list[str]:
    """The RL baselines of the campaign's latest plan (stages/baselines.py `campaign_plans`) not in
    the success table yet: trained and not evaluated; training (its pace, and when it ends at that
    pace), to resume or stopped (at their latest progress, and where a restart resumes them); or
    waiting for a worker; nothing when there are none. `holder`: the run holding the workspace now
    (flows/run_lock.py `run_holder`), or None."""
    plans = campaign_plans(models, campaign)
    training = agents_in_training(models, catalog, plans)  # first: one registering meanwhile shows twice, not never
    running = holder is not None and holder.get("campaign") == campaign
    started = _run_started(holder) if running else None
    rows = []
    for summary in catalog.query(
            "SELECT s.summary FROM stage_runs s WHERE s.stage = ? AND s.campaign = ? AND list_contains(?, s.unit_key) "
            "AND NOT EXISTS (SELECT 1 FROM evaluations v "
            "WHERE v.model_key = s.unit_key AND v.campaign = s.campaign AND v.suite = ?) ORDER BY s.finished_at",
            [BASELINES_STAGE, campaign, list(plans), CAMPAIGN_SUITE]):
        trained = json.loads(summary[0])
        rows.append([f"{AGENT_NAMES.get(trained['algorithm'], trained['algorithm'])} ({trained['family']})",
                     "trained, not evaluated yet", f"{trained['steps_taken']:,} / {trained['env_steps']:,}",
                     f"{trained['episodes']:,} ({trained['successes']:,})", "–", "–", "–"])
    for agent in training:
        name = f"{AGENT_NAMES.get(agent.algorithm, agent.algorithm)} ({agent.family})"
        if not agent.started:
            rows.append([name, "waiting", f"0 / {agent.env_steps:,}", "–", "–", "–", "–"])
            continue
        if not running:
            state = "stopped"
        elif started is None or agent.as_of >= started:
            state = "training"
        else:
            state = "to resume"  # this run has not reached it yet: an earlier stage, or no worker free
        resumes = (f"{agent.checkpoint_steps:,} ({_utc(agent.checkpoint_at)})" if agent.checkpoint_at is not None
                   else "0: no checkpoint yet")
        pace = "–"
        if state == "training" and agent.rate and agent.as_of is not None:  # at its own run's pace from then on
            pace = f"{agent.rate:.1f}/s, ends ~{_utc(agent.as_of + (agent.env_steps - agent.done) / agent.rate)}"
        rows.append([name, state, f"{agent.done:,} / {agent.env_steps:,} ({agent.done / agent.env_steps:.0%})",
                     f"{agent.episodes:,} ({agent.successes:,})", _utc(agent.as_of), pace, resumes])
    if not rows:
        return []
    if running:
        now = (f"A `sim2act run` of this campaign holds the workspace (pid {holder.get('pid')} on "
               f"{holder.get('host')}, since {_utc(started) if started is not None else holder.get('since')}).")
    elif holder is not None:
        now = f"Another run (`{holder.get('campaign')}`) holds the workspace; these wait for a run of this campaign."
    else:
        now = "No `sim2act run` holds the workspace now."
    return ["", f"Baselines not in the table yet. {now} A `sim2act run` with the same settings resumes each from its "
            "last checkpoint.", "",
            *_table(["agent", "state", "env steps / budget", "training episodes (succeeded)", "as of",
                     "env steps/s, end (ETA)", "a restart resumes at (checkpoint)"], rows)]


def _reached(points: list[AdaptPoint], start: str, target: float) -> str:
    episodes = episodes_to_reach(points, start, target)
    most = max(p.episodes for p in points)
    if episodes is None:
        return f"not reached within {most}"
    fell = sorted(n for (n, at), seeds in pooled(points).items() if at == start and n > episodes
                  and pooled_score(seeds)[0] < target * pooled_score(seeds)[1])
    # the fewest that reached it: a noisy curve can dip below again at a larger count, and then says so
    return f"**{episodes}**" + (f" (below it again at {', '.join(map(str, fell))})" if fell else "")


def _pooled_cell(seeds: list[AdaptPoint]) -> str:
    """A point's seeds pooled; with several, the lowest and highest of their own rates after."""
    successes, trials = pooled_score(seeds)
    cell = f"{successes}/{trials} = {successes / trials:.0%}"
    if len(seeds) > 1:
        rates = [p.success_rate for p in seeds]
        cell += f" (seeds {min(rates):.0%}–{max(rates):.0%})"
    return cell


def adaptation_markdown(catalog: Catalog, campaign: str) -> list[str]:
    """The latest adaptation's table: success in the shifted domain per number of its episodes,
    fine-tuned from the campaign's champion and from scratch."""
    results = adapt_results(catalog, campaign)
    if not results:
        return ["No adaptation has run for this campaign (`adapt.episodes_per_task` in its config)."]
    result = results[-1]
    domain = result.domain.model_dump(exclude={"enabled"})
    which = f" ({', '.join(result.tasks)})" if 0 < len(result.tasks) <= 12 else ""
    seeds = max(p.seed for p in result.points) + 1
    lines = [f"The campaign's seen tasks{which} in a held-out simulated domain, **a stand-in for the proposal's real-robot "
             "transfer**: " + ", ".join(f"{name} {value}" for name, value in domain.items()) + " (per episode, "
             "outside the campaign's own randomisation). The expert explores it; each model trains on the first "
             "episodes of every task, fine-tuned from the champion "
             f"(`{result.source_model}`) or from scratch" + (f", {seeds} training seeds each (pooled; the lowest and highest seed "
             "in parentheses)" if seeds > 1 else "") + ", and meets the same evaluation episodes there."
             + (" Its friction changes no contact of an object of nominal friction 1 with the table or the fingers: "
                "MuJoCo takes a contact's larger friction, and theirs are larger (docs/evaluation.md)."
                if result.domain.friction[1] < 1.0 else ""), ""]
    cells = {point: _pooled_cell(seeds) for point, seeds in pooled(result.points).items()}
    counts = sorted({p.episodes for p in result.points if p.start != "source"})
    lines += _table(["target-domain episodes", "fine-tuned from Sim2Act", "from scratch"],
                    [[0, cells[0, "source"] + " (the champion as it is)", "–"]]
                    + [[n, cells.get((n, "fine-tuned"), "–"), cells.get((n, "scratch"), "–")] for n in counts])
    # this adaptation's trainings and evaluations (a later champion's adaptation adds its own to the campaign) and
    # the target domain's data they share
    models = sorted({p.model_key for p in result.points})
    [(seconds,)] = catalog.query(
        "SELECT coalesce(sum(wall_s), 0) FROM stage_runs WHERE campaign = ? AND stage <> ? AND (stage NOT IN ('train', "
        "'evaluate') OR unit_key IN (SELECT unit_key FROM models WHERE list_contains(?, model_key)) "
        "OR unit_key IN (SELECT unit_key FROM evaluations WHERE list_contains(?, model_key)))",
        [result.campaign, ADAPT_STAGE, models, models])
    target = result.target_success
    lines += ["", f"Episodes to reach {target:.0%}: fine-tuned {_reached(result.points, 'fine-tuned', target)}, "
                  f"from scratch {_reached(result.points, 'scratch', target)} (the proposal's target: ≤ 50). "
                  f"Compute: {seconds:,.0f} wall seconds over the adaptation's stages (campaign `{result.campaign}`)."]
    return lines + adaptation_by_family(catalog, result)


def adaptation_by_family(catalog: Catalog, result: AdaptResult) -> list[str]:
    """Where the adapted tasks span several families: each family's points alone (its tasks' evaluation
    rows, the seeds pooled) and the episodes each start needed there; the pooled table mixes a family
    that adapts at once with one that never does."""
    families = family_scores(catalog, result)
    return family_table(result, families) if len(families) > 1 else []


FamilyScores = dict[str, tuple[int, dict[str, tuple[int, int]]]]  # family -> (its tasks, model key -> (successes, episodes))


def family_scores(catalog: Catalog, result: AdaptResult) -> FamilyScores:
    """Each family's score of every model of the adaptation, on that family's adapted tasks, from the
    evaluation rows the adaptation made (its episodes per task: rows of another `adapt.eval_episodes`
    left out)."""
    if not result.tasks:  # registered before adapt.tasks: one family's every seen task
        return {}
    per_task = result.points[0].trials // len(result.tasks)
    rows = catalog.query(  # each case once, its latest evaluation: an earlier adaptation (another domain) evaluated
        # the champion on the same cases under the same campaign and model key
        "SELECT family, model_key, count(DISTINCT task_id), sum(successes), sum(episodes) FROM ("
        " SELECT e.* FROM evaluations e LEFT JOIN stage_runs r ON r.unit_key = e.unit_key"
        " WHERE e.campaign = ? AND e.suite = ? AND list_contains(?, e.task_id) AND list_contains(?, e.model_key)"
        " AND e.episodes = ? QUALIFY row_number() OVER (PARTITION BY e.model_key, e.task_id, e.split, e.instruction"
        " ORDER BY r.finished_at DESC NULLS LAST, e.unit_key DESC) = 1) GROUP BY ALL ORDER BY ALL",
        [result.campaign, ADAPT_SUITE, result.tasks, [p.model_key for p in result.points], per_task])
    families: FamilyScores = {}
    for family, model_key, tasks, successes, episodes in rows:
        families.setdefault(family, (int(tasks), {}))[1][model_key] = (int(successes), int(episodes))
    return families


def family_table(result: AdaptResult, families: FamilyScores) -> list[str]:
    rows, target = [], result.target_success
    for family, (tasks, scores) in families.items():
        points = points_of_family(result.points, scores, tasks)
        cells = {point: _pooled_cell(seeds) for point, seeds in pooled(points).items()}
        for n in sorted({p.episodes_per_task for p in points}):
            if n == 0:
                rows.append([family, tasks, 0, cells.get((0, "source"), "–"), "–"])
            else:
                rows.append([family, tasks, n, cells.get((n * tasks, "fine-tuned"), "–"),
                             cells.get((n * tasks, "scratch"), "–")])
        rows.append([family, tasks, f"to reach {target:.0%}", _reached(points, "fine-tuned", target),
                     _reached(points, "scratch", target)])
    return ["", "Per family (the same models on each family's tasks alone; episodes per task, and on the \"to reach\" "
            "row the family's target-domain episodes):", "",
            *_table(["family", "tasks", "episodes per task", "fine-tuned from Sim2Act (0: the champion)", "from scratch"],
                    rows)]


def spec_markdown(catalog: Catalog, campaign: str) -> list[str]:
    """Success per task spec and split per iteration, where the campaign has several specs (a
    long-horizon spec beside its sub-tasks' shows what a curriculum did); else nothing."""
    spec_of = dict(catalog.query("SELECT DISTINCT task_id, spec FROM tasks WHERE campaign = ?", [campaign]))
    specs = sorted(set(spec_of.values()))
    if len(specs) < 2:
        return []
    by_iteration = {  # grouped as if each spec were a family: "<spec>/<split>"
        iteration: group_success([e.model_copy(update={"family": spec_of[e.task_id]}) for e in evaluations])
        for iteration, evaluations in evaluations_by_iteration(catalog, campaign).items()}
    return _split_table("Per task spec (Sim2Act)", by_iteration, specs) if by_iteration else []


def protocol_markdown(catalog: Catalog, campaign: str) -> list[str]:
    """Trainings of one dataset and recipe over several seeds (`sim2act train --set train.seed=N`),
    evaluated alike (`sim2act eval --model ...`): per split, the mean over seeds, their spread and each
    seed's rate, and the pooled Wilson interval."""
    groups = seed_groups(catalog, campaign, CAMPAIGN_SUITE)
    if not groups:
        return ["No dataset of this campaign was trained with several seeds and evaluated on its cases "
                "(`sim2act train --set train.seed=N`, then `sim2act eval --model ...`; docs/evaluation.md)."]
    lines = ["Each row: trainings of one dataset with one recipe, differing only in `train.seed`, every one "
             "evaluated on the campaign's cases; the mean over seeds ± their standard deviation (each seed's "
             "rate), and the pooled episodes with their Wilson 95% interval.", ""]
    splits = [s for s in SPLITS if any(f.group == s for g in groups for f in g.figures)]
    rows = []
    for group, differing in zip(groups, differing_settings(groups)):
        recipe = ", ".join([f"{k} {v}" for k, v in group.recipe.items() if k in ("chunk", "weights", "steps", "members",
                                                                                 "where") and v is not None]
                           + [f"{k} {v}" for k, v in differing.items() if k != "train.where"])
        recipe, seeds = _with_precision(recipe, group.seeds, group.precisions)
        by_split = {f.group: f for f in group.figures}
        coverage = group.coverage()
        rows.append([str(group.iteration), recipe, group.weights, f"{seeds} ({coverage})" if coverage else seeds,
                     *(by_split[s].describe() if s in by_split else "–" for s in splits)])
    lines += _table(["iteration", "recipe (training summary)", "weights evaluated", "seeds", *splits], rows)
    lines += family_seeds_markdown(groups, splits)
    loops = loop_groups(catalog, campaign, groups)  # the deployments read once, for both tables below
    return lines + climb_markdown(climbs(loops)) + ablation_markdown(ablations(loops, groups))


def family_seeds_markdown(groups: list, splits: list[str]) -> list[str]:
    """Where the trainings met tasks of several families (the generalist): each group's figures per family
    and split, in the rows' order above; one family's are the table above."""
    families = sorted({f.group.split("/")[0] for g in groups for f in g.figures if "/" in f.group})
    if len(families) < 2:
        return []
    rows = []
    for group in groups:
        by_group = {f.group: f for f in group.figures}
        for family in families:
            cells = [by_group[f"{family}/{s}"].describe() if f"{family}/{s}" in by_group else "–" for s in splits]
            if any(cell != "–" for cell in cells):
                rows.append([str(group.iteration), family, group.weights, ", ".join(map(str, group.seeds)), *cells])
    return ["", "Per family, the same trainings:", "",
            *_table(["iteration", "family", "weights evaluated", "seeds", *splits], rows)]


def climb_markdown(found: list) -> list[str]:
    """The loop's first iteration trained over seeds against its last, per split (the families' rows are in the
    table above)."""
    if not found:
        return []
    first, last = found[0].first_iteration, found[0].last_iteration
    rows = [[c.first.group, c.first.describe(), c.last.describe(), f"{100 * c.delta:+.1f}", c.reading()]
            for c in found]
    return ["", f"### The loop over seeds: iteration {first} against iteration {last}", "",
            "The loop's own recipe (the rows holding the models its iterations' redeploy stage met, promoted or "
            "not) at its first and its "
            "last iteration trained over several seeds, registered weights; Δ is the difference of the means "
            "over seeds, in points.", "",
            *_table(["split", f"iteration {first}", f"iteration {last}", "Δ points", "reading"], rows)]


def _with_precision(recipe: str, seeds: list[int], precisions: list[str]) -> tuple[str, str]:
    """The recipe and seeds cells with the precision the trainings ran in: in the recipe where every seed
    ran in the same one, per seed where they differ (a seed with no record says "precision not recorded")."""
    named = [p or "precision not recorded" for p in precisions]
    if len(set(named)) > 1:
        return recipe, ", ".join(f"{seed} ({p})" for seed, p in zip(seeds, named))
    if precisions and precisions[0]:
        recipe = f"{recipe}, {precisions[0]}"
    return recipe, ", ".join(map(str, seeds))


def ablation_markdown(found: list) -> list[str]:
    """The ablations: each other recipe of an iteration against the loop's own, seen split, with what differs."""
    if not found:
        return []
    rows = [[str(a.iteration), ", ".join(f"{k} {v}" for k, v in a.changed.items()) or "(the same settings)",
             a.ablation.describe(), a.loop.describe(), f"{100 * a.delta:+.1f}", a.reading()] for a in found]
    return ["", "### Ablations: each recipe against the loop's own", "",
            "Each row: trainings of an iteration's data with one setting changed (or a part of the data left out: "
            "`train.where`), against the recipe the loop trained there (the group holding the iteration's deployed "
            "model), registered weights, seen split; Δ is the difference of the means over seeds, in points.", "",
            *_table(["iteration", "changed from the loop's recipe", "seen, the ablation", "seen, the loop's",
                     "Δ points", "reading"], rows)]


def dataset_rows(catalog: Catalog, campaign: str, explore_units: list[str],
                 filter_units: list[str]) -> list[tuple]:
    """Per family and split of the dataset `explore_units` made: (family, split, tasks in the campaign, tasks
    explored, episodes, env steps, kept episodes, kept triplets, the explore units' shard bytes). A unit's bytes
    count once, under the task it explored: `explore.relabel` files some of its episodes under other tasks."""
    return catalog.query(f"""
        WITH decided AS (
            SELECT episode_id, bool_or(kept) AS kept FROM filter_decisions WHERE list_contains(?, filter_key) GROUP BY ALL),
        explored AS (SELECT * FROM episodes WHERE campaign = ? AND list_contains(?, shard_key)),
        per_task AS (
            SELECT e.task_id, count(*) AS episodes, sum(e.num_steps) AS steps, count(*) FILTER (WHERE d.kept) AS kept,
                   coalesce(sum(e.num_steps) FILTER (WHERE d.kept), 0) AS kept_steps
            FROM explored e LEFT JOIN decided d USING (episode_id) GROUP BY ALL),
        explored_task AS (  -- an explore unit explores one task: the one its episodes not relabelled are filed under
            SELECT shard_key AS unit_key,
                   coalesce(any_value(task_id) FILTER (WHERE coalesce(explorer_stats, '') NOT LIKE '%relabelled_from%'),
                            any_value(task_id)) AS task_id
            FROM explored GROUP BY ALL),
        task_bytes AS (
            SELECT u.task_id, sum(s.num_bytes) AS num_bytes FROM shards s JOIN explored_task u USING (unit_key)
            GROUP BY ALL)
        SELECT t.family, t.split, count(*), count(p.task_id), coalesce(sum(p.episodes), 0), coalesce(sum(p.steps), 0),
               coalesce(sum(p.kept), 0), coalesce(sum(p.kept_steps), 0), coalesce(sum(b.num_bytes), 0)
        FROM {CURRENT_TASK_FAMILIES} t LEFT JOIN per_task p USING (task_id) LEFT JOIN task_bytes b USING (task_id)
        WHERE t.campaign = ? GROUP BY ALL ORDER BY ALL""", [filter_units, campaign, explore_units, campaign])


def dataset_by_family(catalog: Catalog, campaign: str, explore_units: list[str],
                      filter_units: list[str]) -> list[str]:
    """The latest dataset per family and split: tasks in the campaign and explored, episodes and
    triplets explored and kept (by the dataset's own filter units), and the explored shard files' bytes."""
    rows = dataset_rows(catalog, campaign, explore_units, filter_units)
    if not rows:
        return []
    total = [sum(row[i] for row in rows) for i in range(2, len(rows[0]))]
    table = [[family, split, tasks, explored, f"{episodes:,}", f"{steps:,}", f"{kept:,}", f"{triplets:,}",
              f"{size / 1e6:,.0f}"]
             for family, split, tasks, explored, episodes, steps, kept, triplets, size in [*rows, ["all", "", *total]]]
    return ["", "The latest dataset per family and split (a task explored by several units counts once; bytes: its "
            "explore units' shard files as written, before any compaction):", "",
            *_table(["family", "split", "tasks", "explored", "episodes", "env steps", "kept episodes",
                     "kept triplets", "MB"], table)]


def _success_sections(catalog: Catalog, campaign: str, evaluations: dict[int, list[TaskEvaluation]],
                      steps_through: dict[tuple[int, str], int], cases: Counter, models: Path | None,
                      holder: dict | None) -> list[str]:
    """Success per iteration beside the baselines, per family, unseen kind and spec, the seeds, the adaptation.
    `cases`: family -> the cases the last iteration's model met, which every baseline meets (an RL
    agent: its family's); `steps_through`: (iteration, family) -> the environment steps explored
    through that iteration on the family."""
    lines: list[str] = []
    by_iteration = {iteration: group_success(found) for iteration, found in evaluations.items()}
    splits = split_columns(by_iteration)
    rows = [[f"Sim2Act iteration {iteration}" + (" (BC on iteration-0 data)" if iteration == 0 else ""),
             f"{sum(steps for (through, _), steps in steps_through.items() if through == iteration):,}",
             *_cells(groups, splits)]
            for iteration, groups in sorted(by_iteration.items())]
    baselines = baseline_evaluations(catalog, campaign)
    for (agent, family, steps, model_key), met in baselines.items():
        name = (_agent_name(agent, family, model_key, baselines) + (f" ({family})" if family else "")
                + _evaluating(met, cases[family] if family else sum(cases.values())))
        rows.append([name, f"{steps:,}" if steps else "–", *_cells(group_success(met), splits)])
    lines += _table(["agent", "env steps (training data)", *[split.replace("_", " ") for split in splits]], rows)
    if models is not None:
        lines += pending_baselines_markdown(catalog, campaign, models, holder)

    families = sorted({g.group.split("/")[0] for groups in by_iteration.values() for g in groups if "/" in g.group}
                      | {e.family for met in baselines.values() for e in met})
    if len(families) > 1:
        lines += _split_table("Per family (Sim2Act)", by_iteration, families) if by_iteration else []
        lines += family_baselines_markdown(by_iteration, baselines, families, cases, steps_through)
    lines += unseen_by_kind_markdown(evaluations, baselines, unseen_kinds(catalog, campaign), cases)

    lines += spec_markdown(catalog, campaign)

    if evaluations:  # no policy (the baselines alone): no training seeds, no champion to adapt
        lines += ["", "## Training seeds (the results protocol)", "", *protocol_markdown(catalog, campaign)]
        lines += ["", "## Adaptation to a shifted domain", "", *adaptation_markdown(catalog, campaign)]

    return lines


def planned_cases(catalog: Catalog, campaign: str) -> Counter:
    """family -> the evaluation cases the baselines meet (`evaluation_cases`, without held-out wordings) on the
    tasks of the campaign's newest tasks unit. (A run that goes back to an older tasks unit registers nothing new:
    there the count is the newer unit's.)"""
    newest = catalog.query("SELECT unit_key FROM stage_runs WHERE stage = ? AND campaign = ? "
                           "ORDER BY finished_at DESC LIMIT 1", [TASKS_STAGE, campaign])
    tasks = tasks_of_unit(catalog, newest[0][0]) if newest else []
    return Counter(task.family for task, _, _ in evaluation_cases(tasks))


def results_markdown(catalog: Catalog, campaign: str, command: str, models: Path | None = None,
                     holder: dict | None = None) -> str:
    """The report. A campaign whose latest dataset is indexed but not yet evaluated (the generalist's
    million, before its training) gets its dataset and compute sections alone; one of no iteration (iterations: 0)
    its baselines and compute. With `models` (the
    workspace's), the RL baselines not evaluated yet are listed below the table, each as far as it got,
    and whether `holder` (the run holding the workspace now, or None) is training them.

    Raises:
        ValueError: the campaign has neither an evaluated iteration nor an indexed dataset here."""
    evaluations = evaluations_by_iteration(catalog, campaign)
    latest = catalog.query(  # the last dataset's: every iteration's exploration, nothing older
        f"SELECT explore_units, filter_units FROM {CURRENT_ITERATIONS} WHERE campaign = ? ORDER BY iteration DESC LIMIT 1",
        [campaign])
    # no iteration explored or evaluated, but baselines evaluated or planned (iterations: 0, mid-training included)
    baselines_alone = not evaluations and not latest and bool(
        baseline_evaluations(catalog, campaign) or (models is not None and campaign_plans(models, campaign)))
    if not (evaluations or latest or baselines_alone):
        # a campaign of no iteration (the baselines alone) has no `iterations` row: its evaluations on its own
        # tasks (suite campaign) name it, or mid-training its agents' plans
        held = sorted({name for (name,) in catalog.query(
            "SELECT campaign FROM iterations UNION SELECT campaign FROM evaluations WHERE suite = ?", [CAMPAIGN_SUITE])}
            | ({plan["campaign"] for plan in all_plans(models).values()} if models is not None else set()))
        raise ValueError(f"campaign {campaign!r} has no evaluated iteration in this warehouse ("
                         + (f"it holds {', '.join(map(repr, held))}: name it with --preset, --config or --set name=...)"
                            if held else "it holds no campaign yet)"))
    [(explore_units, filter_units)] = latest or [([], [])]
    explored = catalog.query(
        "SELECT iteration, sum(num_steps), count(*), count(DISTINCT task_id), count(DISTINCT instruction) "
        "FROM episodes WHERE campaign = ? AND list_contains(?, shard_key) GROUP BY iteration ORDER BY iteration",
        [campaign, explore_units])
    # (iteration, family) -> env steps explored through that iteration: each iteration's dataset holds the earlier ones'
    steps_through: Counter = Counter()
    iterations = {row[0] for row in explored} | set(evaluations)
    for iteration, family, steps in catalog.query(
            "SELECT e.iteration, coalesce(f.family, ''), sum(e.num_steps) FROM episodes e "
            f"LEFT JOIN {CURRENT_TASK_FAMILIES} f ON f.campaign = e.campaign AND f.task_id = e.task_id "
            "WHERE e.campaign = ? AND list_contains(?, e.shard_key) GROUP BY ALL", [campaign, explore_units]):
        for through in (i for i in iterations if i >= iteration):
            steps_through[through, family] += int(steps)

    lines = [f"# Results: campaign `{campaign}`", "",
             f"Made by `{command}` on {datetime.date.today().isoformat()} from the warehouse "
             f"`{catalog.warehouse}`. Success on the campaign's evaluation cases (every model and "
             "baseline meets the same episodes: seeds derive from campaign, task and episode), pooled "
             "per split, the Wilson 95% interval in parentheses.", "",
             "## Success per iteration and against the baselines", ""]
    if baselines_alone:  # iterations: 0, the baselines alone: they meet the campaign's tasks' cases
        lines += ["No iteration: the campaign measures its baselines alone (iterations: 0).", ""]
        lines += _success_sections(catalog, campaign, evaluations, steps_through, planned_cases(catalog, campaign),
                                   models, holder)
    elif not evaluations:
        lines += ["No iteration of this campaign is evaluated yet: its dataset and compute follow."]
    else:
        # the cases a baseline meets: the last iteration's model's, less held-out wordings (stages/baselines.py
        # evaluates the canonical and paraphrase cases; a wording no template uses is a test of the policy's reading)
        cases = Counter(e.family for e in evaluations[max(evaluations)] if e.split != HELD_OUT_WORDING)
        lines += _success_sections(catalog, campaign, evaluations, steps_through, cases, models, holder)

    if not baselines_alone:  # no iteration explored: no dataset
        lines += dataset_markdown(catalog, campaign, explored, explore_units, filter_units)
    lines += compute_markdown(catalog, campaign)
    return "\n".join(lines) + "\n"


def dataset_markdown(catalog: Catalog, campaign: str, explored: list[tuple], explore_units: list[str],
                     filter_units: list[str]) -> list[str]:
    """The dataset per iteration (`explored`: iteration, steps, episodes, tasks, instructions) and per family."""
    lines = ["", "## Dataset per iteration", ""]
    dataset = {i: (selected, kept, triplets) for i, selected, kept, triplets in catalog.query(
        f"SELECT iteration, episodes, kept_episodes, triplets FROM {CURRENT_ITERATIONS} WHERE campaign = ?", [campaign])}
    explorers = {}
    for iteration, explorer, episodes in catalog.query(
            "SELECT iteration, explorer, count(*) FROM episodes WHERE campaign = ? AND list_contains(?, shard_key) "
            "GROUP BY ALL ORDER BY ALL", [campaign, explore_units]):
        explorers.setdefault(iteration, []).append(f"{explorer}: {episodes}")
    rows = []
    for iteration, steps, count, tasks, instructions in explored:
        selected, kept, triplets = dataset.get(iteration, (0, 0, 0))
        rows.append([iteration, count, f"{steps:,}", tasks, instructions, "; ".join(explorers.get(iteration, [])),
                     f"{kept} / {selected}", f"{triplets:,}"])
    lines += _table(["iteration", "episodes explored", "env steps", "tasks", "instructions", "explorers (episodes)",
                     "dataset: episodes kept / in selection", "dataset triplets"], rows)
    return lines + dataset_by_family(catalog, campaign, explore_units, filter_units)


def compute_markdown(catalog: Catalog, campaign: str) -> list[str]:
    """Per stage and iteration: the units' summed wall seconds, the elapsed and the running hours."""
    lines = ["", "## Compute", "",
              f"Per stage, as the stages recorded their units: the units' wall seconds summed (an explore unit holds one "
              f"core, so there they are CPU-seconds; a training holds `train.threads`), the stage's elapsed time "
              f"(first unit's start to last unit's end, resumes included) and its running time (the hours in which "
              f"at least one of its units was in flight: the elapsed time less the pauses between a stop and its "
              f"resume). The report ran on {platform.machine()} with {os.cpu_count()} CPU(s) "
              f"({platform.platform(terse=True)}); the campaign ran where its workspace was made.", ""]
    spans: dict[tuple[str, int], list[tuple[float, float]]] = {}
    for stage, iteration, start, end in catalog.query(
            "SELECT CASE WHEN v.model_key = ? OR b.unit_key IS NOT NULL THEN 'evaluate (baselines)' ELSE s.stage END, "
            "s.iteration, epoch(s.finished_at) - s.wall_s, epoch(s.finished_at) "
            "FROM stage_runs s "
            "LEFT JOIN evaluations v ON v.unit_key = s.unit_key "
            "LEFT JOIN stage_runs b ON b.stage = ? AND b.unit_key = v.model_key "
            "WHERE s.campaign = ? AND (v.unit_key IS NULL OR v.suite = ?) ORDER BY s.iteration, s.finished_at",
            [EXPERT, BASELINES_STAGE, campaign, CAMPAIGN_SUITE]):
        spans.setdefault((stage, iteration), []).append((start, end))
    rows = []
    for (stage, iteration), group in spans.items():  # in the query's order: by iteration, then first unit's end
        seconds = sum(end - start for start, end in group)
        elapsed = max(end for _, end in group) - min(start for start, _ in group)
        rows.append([stage, iteration, len(group), f"{seconds:,.0f}", f"{seconds / 3600:,.2f}", f"{elapsed / 3600:,.2f}",
                     f"{running_seconds(group) / 3600:,.2f}"])
    return lines + _table(["stage", "iteration", "units", "wall s (summed)", "unit-hours", "elapsed h", "running h"], rows)
