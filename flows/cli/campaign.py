"""Campaign commands: run a campaign, train or evaluate a model on it, report its results."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from envs.pool import log_stages_to_stderr
from flows.cli.common import (Commands, add_campaign_options, add_config_options, campaign_config, check_tracking_server,
                              configure_environment, non_negative_int, open_catalog, output_file,
                              same_campaign_flags)
from flows.lifetime import ends_with_its_server, watch
from schemas.config import Acting, CampaignConfig, ConfigError
from schemas.experts import TARGET, ExpertRow
from schemas.tasks import FAMILIES, TaskRecord
from schemas.workspace import Workspace, write_text_atomically

MODEL_REF = "champion, @alias, 3, v3, name/3, name@alias (the registry), or a model key train-..."  # --model
SPLIT_CHOICES = ("seen", "unseen", "unseen_paraphrase", "held_out_wording")  # --split: the evaluation's splits


def cmd_run(args: argparse.Namespace) -> int:
    config = campaign_config(args, {} if args.iterations is None else {"iterations": args.iterations})
    from envs.registry import check_render
    from envs.suite import generate_tasks, short_horizons, weak_tasks_left_out
    from warehouse.capacity import check_disk
    from warehouse.training_reader import check_where

    tasks = generate_tasks(config.tasks, config.seed)  # a task config that cannot run is refused here, before any work
    if not any(t.split == "seen" for t in tasks):  # nothing to explore: the filter would keep nothing, an hour in
        raise ConfigError(f"tasks: expected at least one seen task to explore, got none of {len(tasks)} (every colour "
                          "or task held out: tasks.colours, tasks.unseen_colours, tasks.specs)")
    check_render(config.render, tasks)
    check_where(config.train.where)
    check_agent_families(config, tasks)
    check_budgets(config, tasks)
    if config.adapt.episodes_per_task:
        from stages.adapt import adapted_tasks

        adapted_tasks(config, tasks)  # adapt.tasks that are not the campaign's seen tasks: one line, before any work
    workspace, catalog = open_catalog(args)
    to_explore = config
    if args.continue_campaign and catalog.path.exists():  # as bootstrap continues it: one iteration more
        from stages.redeploy import continued

        to_explore = continued(config, workspace)
    estimate = check_disk(workspace.root, to_explore, tasks, catalog)  # a campaign the disk cannot hold: one line
    configure_environment(workspace)
    check_tracking_server(workspace)  # an MLflow server named by MLFLOW_TRACKING_URI answers, or one line
    catalog.store.check_reachable()  # shards on S3: the store answers (and takes the keys), or one line
    workspace.create()
    watch()  # the temporary Prefect server and the workers end with this command, however it ends
    print(
        f"sim2act: campaign {config.name!r}, "
        f"{f'{to_explore.iterations} iteration(s)' if to_explore.iterations else 'no iteration (the baselines alone)'}, "
        f"workspace {workspace.root}",
        flush=True,
    )
    weak = weak_tasks_left_out(config.tasks)
    if weak:
        print(f"sim2act: {len(weak)} task(s) left out, their scripted expert below {TARGET:.0%} (docs/experts.md; "
              f"tasks.weak_experts: keep uses them): {', '.join(weak)}", flush=True)
    if short := short_horizons(config.tasks, tasks):
        print(f"sim2act: {short}", flush=True)
    kept = experts_under_campaign(workspace, config, tasks)
    if len(kept) < len(tasks):  # the refusal above counted every task, to refuse before measuring: the line, the kept
        tasks, estimate = kept, check_disk(workspace.root, to_explore, kept, catalog)
    if estimate.steps:
        seen = sum(t.split == "seen" for t in tasks)
        print(f"sim2act: {len(tasks)} task{'s' * (len(tasks) != 1)} ({seen} explored); about {estimate.steps:,} steps and "
              f"{estimate.bytes / 1e9:.2f} GB to explore over {estimate.iterations} iteration(s)", flush=True)
    from flows.bootstrap import bootstrap

    with ends_with_its_server(f"run `{args.command_line}` again to resume"):
        bootstrap(config=config, workspace=str(workspace.root), continue_campaign=args.continue_campaign)
    from dashboards.report import campaign_summary

    same = same_campaign_flags(args)
    print("\n" + campaign_summary(catalog, config.name, [
        f"the results table (iterations, per spec, baselines):  sim2act report {same}",
        f"dashboard (episodes, videos, SQL panels), MLflow UI:  sim2act up {same}",
        f"the warehouse in SQL:  sim2act sql \"SELECT * FROM task_success\" --workspace {workspace.root}",
        *([f"the champion on any split or task file:  sim2act eval --model champion {same}"] if to_explore.iterations
          else []),
    ]), flush=True)
    return 0


def check_agent_families(config: CampaignConfig, tasks: list[TaskRecord]) -> None:
    """baselines.families names only families an RL agent of the campaign would train on, said in one line before
    any work (without an RL agent asked for, there is nothing for it to name)."""
    from policies.rl_agent import RL_ALGORITHMS
    from stages.baselines import planned_agents

    if config.baselines.families is None or not set(RL_ALGORITHMS) & set(config.baselines.agents):
        return
    everywhere = config.model_copy(update={"baselines": config.baselines.model_copy(update={"families": None})})
    trainable = {family for _, family, _ in planned_agents(everywhere, tasks)}
    idle = [family for family in config.baselines.families if family not in trainable]
    if idle:
        raise ConfigError(f"baselines.families: expected families an RL agent of baselines.agents trains on (seen "
                          f"tasks it acts in: {', '.join(sorted(trainable)) or 'none'}), got {', '.join(idle)}")


def check_budgets(config: CampaignConfig, tasks: list[TaskRecord]) -> None:
    """A campaign of no iteration explores nothing to take an RL agent's budget from: each planned agent's family
    needs one in baselines.env_steps (a mapping may leave a family out), said in one line before any work."""
    if config.iterations:
        return
    from stages.baselines import planned_agents, rl_budget

    unbudgeted = [f"{algorithm} on {family}" for algorithm, family, _ in planned_agents(config, tasks)
                  if not rl_budget(config.baselines.env_steps, family, {})]
    if unbudgeted:
        raise ConfigError(f"baselines.env_steps: expected a budget for every RL agent where iterations is 0, got "
                          f"{config.baselines.env_steps} and none for {', '.join(unbudgeted)}")


def experts_under_campaign(workspace: Workspace, config: CampaignConfig, tasks: list[TaskRecord]) -> list[TaskRecord]:
    """The campaign's tasks less those whose expert is below target under its own randomisation: measured here
    where the workspace holds no row yet (a line per tenth, with rate and ETA), said in one line, before the flow
    (which finds the rows measured)."""
    import time

    from envs.expert_check import EPISODES, checks_experts, experts_under, felt_apart, said
    from stages.generate_tasks import campaign_tasks, left_out_line

    if not checks_experts(config.tasks.weak_experts, config.randomise):
        return tasks
    unmeasured = len(tasks) - len(experts_under(workspace, tasks, config.randomise, 1, measure=False))
    started, done = time.monotonic(), []

    def report(row: ExpertRow) -> None:
        done.append(row)
        if len(done) == unmeasured or len(done) % max(unmeasured // 10, 1) == 0:
            rate = len(done) / (time.monotonic() - started)
            print(f"sim2act: experts {len(done)}/{unmeasured} tasks, {rate * 60:.1f} tasks/min, "
                  f"ETA {(unmeasured - len(done)) / rate:.0f}s", flush=True)

    if unmeasured:
        print(f"sim2act: measuring the scripted experts of {unmeasured} task(s) under this campaign's randomisation "
              f"({said(felt_apart(config.randomise))}), {EPISODES} episodes each without a camera", flush=True)
    kept, weak = campaign_tasks(workspace, config, measure=True, progress=report)
    if weak:
        print(f"sim2act: {left_out_line(weak, config, kept)}", flush=True)
    return kept


def cmd_train(args: argparse.Namespace) -> int:
    config = campaign_config(args)
    from flows.run_lock import reading_shard_files
    from flows.tracking import Tracking
    from stages.generate_tasks import campaign_tasks, tasks_unit_key
    from stages.index import latest_index
    from stages.train import run_train
    from warehouse.tasks import load_embeddings
    from warehouse.training_reader import check_where

    check_where(config.train.where)
    workspace, catalog = open_catalog(args)
    dataset = latest_index(workspace, config.name, args.iteration, config)
    if dataset is None:
        which = f"iteration {args.iteration}" if args.iteration is not None else "any iteration"
        raise ConfigError(f"--iteration: campaign {config.name!r} has no dataset for {which} in {workspace.root} "
                          "decided by this config's filter settings (run `sim2act run` with this config first)")
    tasks_key = tasks_unit_key(config, campaign_tasks(workspace, config)[0])
    if not catalog.is_registered(tasks_key):
        raise ConfigError(f"tasks: this config's tasks were never generated in {workspace.root} (run `sim2act run` first)")
    configure_environment(workspace)
    check_tracking_server(workspace)  # an MLflow server named by MLFLOW_TRACKING_URI answers, or one line
    log_stages_to_stderr()
    watch()  # the loader workers end with this command, however it ends
    tracking = Tracking(workspace, config)
    run_id = tracking.iteration_run(tracking.campaign_run(), dataset.iteration)
    print(f"sim2act: training on campaign {config.name!r} iteration {dataset.iteration}'s dataset "
          f"({dataset.triplets:,} triplets), MLflow run {run_id}", flush=True)
    try:
        with reading_shard_files(workspace, "train"):  # a compaction would delete the files its dataset lists
            result = run_train(
                workspace, config, dataset.iteration, dataset, tasks_key,
                load_embeddings(workspace, tasks_key, config.train.model.language_encoder),
                on_metrics=tracking.step_logger(run_id, "train."),
            )
    except KeyboardInterrupt:  # runs this command opened do not stay RUNNING
        tracking.finish_created("KILLED")
        raise
    except Exception:
        tracking.finish_created("FAILED")
        raise
    if result.skipped:
        state = "already trained"
    else:
        tracking.log_training_dataset(run_id, result.dataset_digest, result.dataset_shards, result.samples)
        resumed = f"resumed at step {result.resumed_at_step}, " if result.resumed_at_step else ""
        state = f"{resumed}final loss {result.history[-1]['loss']:.4f}"
    tracking.finish_created()  # another train.seed's campaign and iteration runs, opened by this command
    print(f"model {result.model_key}: {state}; checkpoint {result.checkpoint}")
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    if args.episodes is not None and args.episodes < 1:
        raise ConfigError(f"--episodes: at least 1, got {args.episodes}")
    config = campaign_config(args, {} if args.episodes is None else {"evaluate": {"episodes_per_task": args.episodes}})
    workspace, _ = open_catalog(args)
    configure_environment(workspace)
    check_tracking_server(workspace)  # an MLflow server named by MLFLOW_TRACKING_URI answers, or one line
    log_stages_to_stderr()
    from envs.registry import check_render
    from flows.model_eval import check_model_fits, check_model_ref, eval_cases, instruction_embeddings, resolve_model
    from flows.tracking import Tracking
    from stages.evaluate import Agent, evaluate_model, evaluated_key, episodes_per_split

    for ref in args.model:  # a reference that cannot be one: said first, not after the tasks' checks
        check_model_ref(ref, config)
    suite, cases = eval_cases(workspace, config, args.tasks, args.split, args.family)  # bad input refused here, first
    per_split = episodes_per_split(config, cases)  # the split's whole size, a family's cases or not: the same units
    if args.family:
        cases = [case for case in cases if case[0].family == args.family]
        if not cases:
            raise ConfigError(f"--family: {suite} has no {args.family} case{' in split ' + args.split if args.split else ''}")
    check_render(config.render, [task for task, _, _ in cases])  # a view a case's scene lacks: one line, here
    models = [resolve_model(workspace, config, ref) for ref in args.model]
    for model in models:
        check_model_fits(config, model)
    embeddings = instruction_embeddings(workspace, config, cases)
    watch()  # the rollout workers end with this command, however it ends
    tracking = Tracking(workspace, config)
    by_model = []
    for model in models:
        # the last weights are another agent than the registered (averaged) ones: their own evaluation units
        model_key = evaluated_key(model.model_key, args.weights)
        run_id = tracking.evaluation_run(model_key, suite, model.label)
        print(f"sim2act: evaluating {model.label} ({model.model_key}, trained at iteration {model.iteration}, "
              f"{weights_of_checkpoint(model.checkpoint, args.weights)} weights) on {len(cases)} case(s) of {suite}, "
              f"{'/'.join(map(str, sorted({per_split[split] for _, split, _ in cases})))} episodes each; "
              f"MLflow run {run_id}", flush=True)
        evaluations, skipped = evaluate_model(workspace, config, model.iteration, model_key,
                                              Agent(kind="sim2act", path=model.checkpoint, weights=args.weights),
                                              cases, embeddings, suite, per_split=per_split)
        if skipped < len(evaluations):
            tracking.log_evaluation(run_id, evaluations)
        tracking.finish(run_id)
        _print_evaluations(evaluations, {task.task_id: task.spec for task, _, _ in cases})
        by_model.append(evaluations)
    if len(models) > 1:
        from dashboards.protocol import protocol_success

        print(f"\nover the {len(models)} models (training seeds): mean ± spread across them (each one's rate), "
              "pooled episodes [Wilson 95%]")
        for figure in protocol_success(by_model):
            print(f"{figure.group:<24} {figure.describe()}")
    return 0


def cmd_shadow(args: argparse.Namespace) -> int:
    if args.episodes is not None and args.episodes < 1:
        raise ConfigError(f"--episodes: at least 1, got {args.episodes}")
    if args.steps is not None and args.steps < 1:
        raise ConfigError(f"--steps: expected at least 1, got {args.steps}")
    # --episodes N: N per case, drawn as the evaluation draws them (so its first N, and more the same way)
    config = campaign_config(args, {} if args.episodes is None else
                             {"evaluate": {"episodes_per_task": args.episodes, "episodes_per_split": None}})
    workspace, _ = open_catalog(args)
    configure_environment(workspace)
    from envs.pool import Progress, run_in_pool
    from envs.registry import check_render
    from envs.shadow import markdown, placement_markdown
    from flows.model_eval import (check_model_fits, check_model_ref, eval_cases, instruction_embeddings, resolve_model,
                                  started_as_trained, trained_seeds)
    from policies.policy import weights_of
    from stages.evaluate import Agent, evaluation_units, shadow_unit

    check_model_ref(args.model, config)  # a reference that cannot be one: said first, not after the tasks' checks
    suite, cases = eval_cases(workspace, config, None, args.split)  # bad input refused here, before any work
    known = {task.task_id for task, _, _ in cases}
    unknown = sorted(set(args.task or ()) - known)
    if unknown:
        raise ConfigError(f"--task: expected task ids of the campaign's {args.split or 'evaluation'} cases "
                          f"({', '.join(sorted(known))}), got {', '.join(unknown)}")
    check_render(config.render, [task for task, _, _ in cases])
    model = resolve_model(workspace, config, args.model)
    check_model_fits(config, model)
    state = checkpoint_state(model.checkpoint)
    acting, weights = acting_of(args, state), weights_of(state, args.weights)
    del state  # the weights load in the workers; the CLI needed the config and the weights' name
    # the units of all the split's cases, then the asked tasks': each case keeps the episodes `sim2act eval` plays
    units = [unit for unit in evaluation_units(workspace, config, model.model_key,
                                               Agent(kind="sim2act", path=model.checkpoint, weights=args.weights,
                                                     acting=acting),
                                               cases, instruction_embeddings(workspace, config, cases), suite)
             if not args.task or unit.task.task_id in args.task]
    if args.placements == "trained":  # the same cases, started where the model's training episodes started
        units = started_as_trained(units, trained_seeds(workspace, config, model, [unit.task.task_id for unit in units]))
    if args.steps is not None:  # the same episodes cut short: a horizon of N steps
        units = [unit.model_copy(update={"task": unit.task.model_copy(update={"horizon": min(args.steps, unit.task.horizon)})})
                 for unit in units]
    log_stages_to_stderr()
    watch()  # the rollout workers end with this command, however it ends
    print(f"sim2act: shadowing {model.label} ({model.model_key}) on {len(units)} case(s), "
          f"{'/'.join(str(n) for n in sorted({len(u.seeds) for u in units}))} episodes each", flush=True)
    shadows = {}
    progress = Progress(logging.getLogger("sim2act.shadow"), "shadow", len(units), "cases", "episodes")
    try:
        for unit, shadow, _ in run_in_pool(shadow_unit, units, config.evaluate.workers, lambda u: u.task.task_id):
            shadows[unit.unit_key] = shadow
            progress.advance(1, shadow.episodes)
    finally:
        progress.close()
    how = (f"{weights} weights" + (f", acting: {acting.describe()}" if acting else "")
           + (f", the first {args.steps} step{'s' * (args.steps > 1)} of each episode" if args.steps else "")
           + (", from its training episodes' placements" if args.placements == "trained" else ""))
    cases_shadowed = [shadows[u.unit_key] for u in units]
    print(markdown(cases_shadowed, f"{model.label} ({how})"))
    if placements := placement_markdown(cases_shadowed, trained=args.placements == "trained"):
        print(f"\n{placements}")
    return 0


def checkpoint_state(path: str) -> dict:
    import torch

    return torch.load(path, map_location="cpu", weights_only=False)


def weights_of_checkpoint(path: str, weights: str) -> str:
    from policies.policy import weights_of

    return weights_of(checkpoint_state(path), weights)


def acting_of(args: argparse.Namespace, state: dict) -> Acting | None:
    """--execution, --execute-steps, --ensemble-decay: how the checkpoint turns its chunks into actions
    here (schemas.config.Acting), checked against its model before any work; None: as it trained.

    Raises:
        ConfigError: a value out of range, or one that does not apply to this model."""
    from pydantic import ValidationError

    from policies.policy import model_config_of

    given = {"execution": args.execution, "execute_steps": args.execute_steps, "ensemble_decay": args.ensemble_decay}
    if all(value is None for value in given.values()):
        return None
    try:
        acting = Acting(**given)
    except ValidationError as error:
        first = error.errors()[0]
        raise ConfigError(f"--{str(first['loc'][0]).replace('_', '-')}: {first['msg'].lower()}, "
                          f"got {first['input']}") from None
    model = model_config_of(state)
    if model.chunk == 1:
        first = next(name for name, value in given.items() if value is not None).replace("_", "-")
        raise ConfigError(f"--{first}: the model predicts one action per observation (chunk 1): it acts one way")
    execution = acting.execution or model.execution
    if acting.execute_steps is not None and execution != "receding":
        raise ConfigError(f"--execute-steps: applies to --execution receding, got execution {execution}")
    if acting.ensemble_decay is not None and execution != "temporal_ensemble":
        raise ConfigError(f"--ensemble-decay: applies to --execution temporal_ensemble, got execution {execution}")
    if acting.execute_steps is not None and acting.execute_steps > model.chunk:
        raise ConfigError(f"--execute-steps: expected at most the model's chunk ({model.chunk}), "
                          f"got {acting.execute_steps}")
    try:  # whatever else the model's own validation asks, before a worker meets it
        applied = acting.applied_to(model)
    except ValueError as error:
        raise ConfigError(f"--execution: {error}") from None
    if applied.execution == "receding" and acting.execute_steps is None:  # said in the caption: the steps it takes
        acting = acting.model_copy(update={"execute_steps": applied.steps_per_prediction})
    return acting


def _print_evaluations(evaluations, spec_of: dict[str, str]) -> None:
    from stages.evaluate import goal_confusions, group_success

    def interval(low: float, high: float) -> str:
        return f"[{low:4.0%}, {high:4.0%}]"

    print(f"\n{'task':<34} {'split':<18} {'success':>9} {'':>5}  Wilson 95%    length  instruction")
    for t in evaluations:
        print(f"{t.task_id:<34} {t.split:<18} {t.successes:>4}/{t.episodes:<4} {t.success_rate:>5.0%}  "
              f"{interval(t.ci_low, t.ci_high)}  {t.mean_length:6.1f}  {t.instruction}")
    print()
    for g in group_success(evaluations):
        print(f"{g.group:<53} {g.successes:>4}/{g.episodes:<4} {g.success_rate:>5.0%}  "
              f"{interval(g.ci_low, g.ci_high)}  {g.mean_length:6.1f}")
    confusions = [c for c in goal_confusions(evaluations, spec_of) if c.same_spec + c.other_spec]
    if confusions:
        print("\nfailed episodes that ended at a goal the words did not name (the colour misread: same task "
              "in another colour; the object misread: another task)")
        for c in confusions:
            commonest = ", ".join(f"{task} -> {done} x{n}" for task, done, n in c.commonest)
            print(f"{c.split:<18} {c.failures:>4} failed: {c.same_spec:>4} colour misread, {c.other_spec:>4} "
                  f"object misread   commonest: {commonest}")


def cmd_report(args: argparse.Namespace) -> int:
    config = campaign_config(args)
    from dashboards.results import results_markdown

    from flows.run_lock import run_holder

    workspace, catalog = open_catalog(args)
    try:
        text = results_markdown(catalog, config.name, args.command_line, workspace.models, run_holder(workspace))
    except ValueError as exc:
        raise ConfigError(f"report: {exc}") from None
    if args.out is None:
        print(text, end="")
        return 0
    write_text_atomically(args.out, text)
    print(f"sim2act: wrote {args.out}")
    return 0


def cmd_config(args: argparse.Namespace) -> int:
    from schemas.config_text import config_yaml

    print(config_yaml(campaign_config(args), changed=args.changed, said=args.command_line), end="")
    return 0


def register(commands: Commands) -> None:
    def campaign_command(name: str, help: str, handler) -> argparse.ArgumentParser:
        command = add_campaign_options(commands.add_parser(name, help=help))
        command.set_defaults(handler=handler)
        return command

    run = campaign_command("run", "run a bootstrap campaign (embedded: no server needed)", cmd_run)
    run.add_argument("--iterations", type=non_negative_int,
                     help="number of bootstrap iterations (0: the baselines alone, baselines.agents)")
    run.add_argument("--continue", dest="continue_campaign", action="store_true",
                     help="one iteration past the campaign's latest finished one (what the nightly deployment runs)")
    campaign_command("train", "train the model alone on a campaign's dataset (resumes if killed)", cmd_train
                     ).add_argument("--iteration", type=non_negative_int, help="whose dataset (default: the campaign's latest)")

    evaluate = campaign_command("eval", "evaluate any model on the campaign's tasks, one split, or a task file",
                                cmd_eval)
    evaluate.add_argument("--model", required=True, action="append", metavar="REF",
                          help=MODEL_REF + "; repeat it for several trainings (seeds): each is evaluated, then the "
                               "results protocol's mean, spread and pooled interval over them")
    evaluate.add_argument("--weights", choices=("registered", "final"), default="registered",
                          help="registered: the weights the training registers (its moving average, train.ema); "
                               "final: its last weights")
    which = evaluate.add_mutually_exclusive_group()
    which.add_argument("--tasks", type=Path, metavar="FILE", help="a task spec YAML file: its tasks, all colours")
    which.add_argument("--split", choices=SPLIT_CHOICES,
                       help="only this split's cases (held_out_wording: seen tasks in words the generator never uses)")
    evaluate.add_argument("--episodes", type=int, help="episodes per case (default: the config's evaluate.episodes_per_task)")
    evaluate.add_argument("--family", choices=FAMILIES, help="only this family's cases (of the campaign's, a split's or a file's)")

    shadow = campaign_command("shadow", "a model's evaluation episodes with the noiseless expert asked at every "
                              "state: where they part (a grasp tried short, a slow hand, a drop)", cmd_shadow)
    shadow.add_argument("--model", required=True, metavar="REF", help=MODEL_REF)
    shadow.add_argument("--weights", choices=("registered", "final"), default="registered",
                        help="registered: the weights the training registers (its moving average); final: its last")
    shadow.add_argument("--split", choices=SPLIT_CHOICES, help="only this split's cases")
    shadow.add_argument("--task", action="append", metavar="ID", help="only this task's cases (repeatable)")
    shadow.add_argument("--episodes", type=int,
                        help="episodes per case, drawn as sim2act eval draws them: its first N (default: as "
                             "many as the evaluation plays)")
    shadow.add_argument("--steps", type=int, metavar="N",
                        help="play only the first N steps of each episode (the placement table reads the first: "
                             "--steps 1 gives it in seconds; success then means within N steps)")
    shadow.add_argument("--placements", choices=("evaluation", "trained"), default="evaluation",
                        help="where episodes start: the evaluation's placements (held out), or those the model's "
                             "training episodes started from (explore's seeds, up to its iteration): the two placement "
                             "tables side by side tell localising from memorising")
    shadow.add_argument("--execution", choices=("temporal_ensemble", "receding"),
                        help="a chunked model acting otherwise than it trained to (default: its own): "
                             "temporal_ensemble averages every chunk's prediction for a step, receding executes the "
                             "first --execute-steps of each")
    shadow.add_argument("--execute-steps", type=int, metavar="N", help="receding: actions executed per prediction")
    shadow.add_argument("--ensemble-decay", type=float, metavar="M", help="temporal_ensemble: weights exp(-M i)")

    campaign_command("report", "the results table: success per iteration beside the baselines, dataset, compute",
                     cmd_report).add_argument("--out", type=output_file, help="write the Markdown here (default: print it)")

    config = add_config_options(commands.add_parser(
        "config", help="the campaign the options name, every field with its value and what it does: YAML that "
                       "--config loads back"))
    config.add_argument("--changed", action="store_true",
                        help="only the fields whose value differs from the default preset's (still a whole campaign "
                             "with --config)")
    config.set_defaults(handler=cmd_config)
