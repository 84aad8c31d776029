#!/bin/bash
# Issue 11 item 4, navigation's second attempt: the generalist trained at the preset's own 20,000 steps (5.1M
# samples, ~1.2M of them navigation's) rather than docs/quality/generalist.sh's 7,000 (~0.5M navigation's). A
# navigation-only probe on the generalist's own navigation episodes reached 83% seen with ~1.0M navigation samples,
# against the generalist's 65% (docs/results-generalist.md, "What the policy cannot see"): this asks whether the
# generalist gets there with its whole mix at the samples the probe had. The results protocol's three seeds, each
# evaluated on the preset's 228 cases x 10 episodes; then each seed's navigation episodes split by where the goal
# starts (in view, out of view from an end room, from the middle room).
#
#   docs/quality/generalist-20k.sh WORKSPACE [SIM2ACT [--set FIELD=VALUE ...]]   # from the repository root; ~9 h on 2 cores
#
# 1. the iteration: explore the million (~1.4 h on 2 cores; item 1's documented command: a workspace that holds it
#    skips it), train it at 20,000 steps under three seeds (~1.7 h each in bf16 where the CPU pays for it), evaluate
#    each on the 228 cases (~0.7 h each); no baselines or adaptation (their rows are generalist.sh's, at 7,000
#    steps, on the same million: its explore keys do not depend on train.*);
# 2. `sim2act report` into WORKSPACE-logs/report-20k.md;
# 3. docs/quality/nav-visibility-probe.py on each of the iteration's models into WORKSPACE-logs/nav-classes-KEY.md.
# Running it again skips what finished and resumes what was cut (an explore or evaluation unit, a training from its
# last checkpoint). Settings after SIM2ACT join every command: beside another busy process (an RL baseline on one
# core) `--set explore.workers=1 --set train.threads=1 --set evaluate.workers=1` (none of them is part of a unit's key,
# so a later run without them resumes the same units; two torch threads on shared cores wait on each other:
# docs/training.md). Logs: WORKSPACE-logs/.
set -euo pipefail
# this checkout's code, also where SIM2ACT is another checkout's install (an editable install imports its own tree)
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
W=${1:?usage: generalist-20k.sh WORKSPACE [SIM2ACT [--set FIELD=VALUE ...]]}
W=${W%/}
S=${2:-sim2act}
PYTHON=$(dirname "$(command -v "$S")")/python
C=(--preset generalist --set render.mesh_detail=0.1 --set evaluate.training_seeds=3 --workspace "$W" "${@:3}")
LOGS=$W-logs
mkdir -p "$LOGS"
trap 'echo "generalist-20k.sh: a step failed; its log is the newest in $LOGS/" >&2' ERR

$S run "${C[@]}" --set 'baselines.agents=[]' --set 'adapt.episodes_per_task=[]' >> "$LOGS/iteration-20k.log" 2>&1
$S report "${C[@]}" | tee "$LOGS/report-20k.md"
# the iteration's models at 20,000 steps: those its evaluations name (a workspace also holding generalist.sh's
# 7,000-step models lists those too; each gets its own file)
for key in $($S sql --format csv --workspace "$W" "SELECT DISTINCT model_key FROM evaluations
                                                    WHERE family = 'navigation' ORDER BY 1" | tail -n +2); do
  "$PYTHON" docs/quality/nav-visibility-probe.py --workspace "$W" --model "$key" --campaign generalist \
    | tee "$LOGS/nav-classes-$key.md"
done
