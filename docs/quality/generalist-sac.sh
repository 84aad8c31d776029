#!/bin/bash
# Issue 11 item 4's SAC rows on a fresh machine, without the generalist's million: SAC from scratch per continuous
# family at the environment steps the generalist's exploration took there (docs/results-generalist.md, item 1:
# MetaWorld 382,023, robosuite 455,956; navigation's actions are discrete, SAC does not act there), on the same
# seen tasks, render and randomisation, then evaluated on the same cases x 10 episodes as the policy and PPO (the
# episodes drawn under this campaign's name: an evaluation's seeds derive from it, so not the same draws).
#
#   docs/quality/generalist-sac.sh WORKSPACE [SIM2ACT [--set ...]]   # from the repository root; ~13-15 h on 2 cores with AVX-512 BF16, ~24 h on AVX2 alone
#
# Settings after SIM2ACT go to the run, e.g. `--set baselines.workers=1 --set baselines.threads=2`: one agent at a
# time on both cores, MetaWorld's first, each evaluated before the next begins (~12 h to MetaWorld's rows on AVX2
# instead of ~19 h; both end ~3 h later than side by side: docs/results-generalist.md). Neither is part of a unit's
# key: a run resumes the same agents from their checkpoints with or without them.
#
# `--set 'baselines.families=[robosuite]'` trains robosuite's SAC alone (MetaWorld's rows in already; the same
# agent's key; the tenth run's command also gave `--set 'baselines.env_steps={robosuite: 455956}'`, the same budget).
#
# Why not docs/quality/generalist-baselines.sh: that one explores the million, trains and evaluates the policy and
# the PPOs first (~5.5-7.5 h on an AMD EPYC), whose rows are in the docs already; six times a workspace went with its
# machine before its SACs finished, and those hours came first each time. Here the campaign has no iteration
# (`--iterations 0`: the baselines alone, on the preset's tasks). Until 2026-12-07 it ran a token iteration 0 first
# (2 episodes a seen task, 77 training steps, its evaluation ~1 h: the ninth run's workspace holds it); the agents'
# keys are the same either way, so a workspace made with it resumes its agents under this script.
# 1. the campaign `generalist-sac`: the preset's tasks, then the two SACs at once, one a worker, each
#    checkpointed every 5,000 environment steps (~10 minutes lost to a kill or a session's end), then their
#    evaluations on their families' cases;
# 2. `sim2act report` into WORKSPACE-logs/report.md (the SAC rows, and a token model's where the workspace has one).
# Running it again skips what finished and resumes what was cut. Logs: WORKSPACE-logs/.
set -euo pipefail
# this checkout's code, also where SIM2ACT is another checkout's install (an editable install imports its own tree)
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
# each worker keeps every scene it opens, as the generalist's baselines ran (docs/quality/generalist-baselines.sh)
export SIM2ACT_SCENES_PER_WORKER=${SIM2ACT_SCENES_PER_WORKER:-64}
W=${1:?usage: generalist-sac.sh WORKSPACE [SIM2ACT [--set ...]]}
W=${W%/}
S=${2:-sim2act}
MORE=("${@:3}")  # the run's own settings (the report needs none of them)
# (the agents' keys read the tasks, render, randomisation and seed: not the token iteration's explore and train
# settings, which the ninth run's command still carried)
C=(--preset generalist --set name=generalist-sac --set render.mesh_detail=0.1 --workspace "$W")
LOGS=$W-logs
mkdir -p "$LOGS"
trap 'echo "generalist-sac.sh: a step failed; its log is $LOGS/baselines.log" >&2' ERR

$S run "${C[@]}" --iterations 0 --set 'adapt.episodes_per_task=[]' --set 'baselines.agents=[sac]' \
  --set 'baselines.env_steps={metaworld: 382023, robosuite: 455956}' --set baselines.checkpoint_every=5000 \
  "${MORE[@]}" >> "$LOGS/baselines.log" 2>&1
$S report "${C[@]}" | tee "$LOGS/report.md"
