#!/bin/bash
# Issue 9 item 5: the third attempt's loop (hard-mix-takeover.yaml), the results protocol's seeds at iterations 0
# and 3, and the ablations of the loop's parts on its last dataset, three training seeds each (docs/results.md).
#
#   docs/quality/hard-mix-ablations.sh WORKSPACE [SIM2ACT]      # from the repository root; ~16 h on 2 cores
#
# 1. the loop: `sim2act run`, one training per iteration (resumes where it stopped);
# 2. train.seed 1 and 2 at iterations 0 and 3 (the protocol's other seeds), each evaluated on the seen split;
# 3. at iteration 3, seeds 0-2 each: the executed actions as targets instead of the expert's labels
#    (train.targets=executed); the expert's own episodes alone (the champion's DAgger episodes left out); the
#    successful episodes alone (the failed ones left out);
# 4. `sim2act report`: its "Training seeds" table pools each recipe's seeds, a row per recipe.
# Every step is resumable or cached, so running the script again skips what finished and resumes what was cut:
# a training from its last checkpoint (every 200 steps), an evaluation per case. Logs: WORKSPACE-ablations/.
set -euo pipefail
# this checkout's code, also where SIM2ACT is another checkout's install (an editable install imports its own tree)
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
W=${1:?usage: hard-mix-ablations.sh WORKSPACE [SIM2ACT]}
S=${2:-sim2act}
C=(--preset hard-mix --config docs/quality/hard-mix-takeover.yaml --workspace "$W")
LOGS=$W-ablations
mkdir -p "$LOGS"

$S run "${C[@]}" --set evaluate.training_seeds=1

unit() {  # NAME ITERATION SEED [--set FIELD=VALUE ...]: train, then evaluate on the seen split
    local name=$1 iteration=$2 seed=$3 key
    shift 3
    grep -q "^$name	" "$LOGS/done.tsv" 2>/dev/null && return 0
    $S train "${C[@]}" --iteration "$iteration" --set train.seed="$seed" "$@" >> "$LOGS/$name.log" 2>&1
    key=$(grep -o "^model train-[0-9a-f]*" "$LOGS/$name.log" | tail -1 | cut -d' ' -f2)
    $S eval "${C[@]}" --model "$key" --split seen >> "$LOGS/$name.log" 2>&1
    printf "%s\t%s\n" "$name" "$key" >> "$LOGS/done.tsv"
}
for seed in 1 2; do unit "iteration0-seed$seed" 0 "$seed"; done
for seed in 1 2; do unit "iteration3-seed$seed" 3 "$seed"; done
# seed by seed across the three ablations, so a cut queue leaves one reading of each part rather than one part
for seed in 0 1 2; do
    unit "executed-seed$seed" 3 "$seed" --set train.targets=executed
    unit "expert-episodes-seed$seed" 3 "$seed" \
        --set "train.where=episode_id IN (SELECT episode_id FROM episodes WHERE explorer = 'expert')"
    unit "successful-episodes-seed$seed" 3 "$seed" --set "train.where=episode_id IN (SELECT episode_id FROM episodes WHERE success)"
done
$S report "${C[@]}" | tee "$LOGS/report.md"
