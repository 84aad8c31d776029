#!/bin/bash
# Issue 11 item 4's RL rows on a fresh machine: the generalist's million, one training of the policy (seed 0) and
# its evaluation, the experts' ceiling, then PPO and SAC per family at the environment steps the family's exploration
# took, all in one workspace, so that one `sim2act report` puts them side by side (docs/results-generalist.md).
#
#   docs/quality/generalist-baselines.sh WORKSPACE [SIM2ACT]   # from the repository root; ~17 h on 2 cores (AMX)
# (the SAC rows alone, without the million, the policy and the PPOs: docs/quality/generalist-sac.sh)
#
# Why not docs/quality/generalist.sh: that script also trains the results protocol's other two seeds and runs the
# adaptation before the baselines (~8 h), whose figures are in the docs already; a workspace that went with its
# machine needs only the baselines again, and they are the long part (~12 h inside the campaign on an AMX Xeon:
# docs/bench-rl.md).
# 1. the iteration: explore the million (~1 h), train seed 0 (~0.7 h), evaluate it on 228 cases x 10 episodes
#    (~0.6 h); the adaptation off; then, in the same command, the experts and the three PPOs (~2.5 h on the two
#    workers) and their evaluations; `sim2act report` into WORKSPACE-logs/report-ppo.md;
# 2. the same command with SAC added: the PPOs are trained and evaluated already (their units are kept), so the
#    two SACs train at once, one a worker (~10-14 h), each checkpointed every 5,000 environment steps (~7.5 minutes
#    lost to a kill or a session's end), then their evaluations;
# 3. `sim2act report` into WORKSPACE-logs/report.md.
# Why PPO first rather than the stage's longest-first order of all five (~1 h sooner to the end): six times a
# workspace went with its machine before its SACs finished (docs/results-generalist.md), and the PPO rows in
# report-ppo.md are out of it ~10 h earlier.
# Running it again skips what finished and resumes what was cut. Logs: WORKSPACE-logs/.
set -euo pipefail
# this checkout's code, also where SIM2ACT is another checkout's install (an editable install imports its own tree)
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
# each worker keeps every scene it opens (the default closes beyond 16): an RL episode draws its task at random from
# the family's 35-44, and the runs since session 53 measured the SACs so (MetaWorld's 44 scenes ~6.3 GB on its
# worker: docs/evaluation.md); a scene closed and made again draws the same frames, so only speed and memory differ
export SIM2ACT_SCENES_PER_WORKER=${SIM2ACT_SCENES_PER_WORKER:-64}
W=${1:?usage: generalist-baselines.sh WORKSPACE [SIM2ACT]}
W=${W%/}
S=${2:-sim2act}
C=(--preset generalist --set render.mesh_detail=0.1 --set train.steps=7000 --workspace "$W")
LOGS=$W-logs
mkdir -p "$LOGS"
trap 'echo "generalist-baselines.sh: a step failed; its log is $LOGS/baselines.log" >&2' ERR

$S run "${C[@]}" --set 'adapt.episodes_per_task=[]' --set 'baselines.agents=[expert,ppo]' \
  --set baselines.checkpoint_every=5000 >> "$LOGS/baselines.log" 2>&1
$S report "${C[@]}" > "$LOGS/report-ppo.md"
$S run "${C[@]}" --set 'adapt.episodes_per_task=[]' --set baselines.checkpoint_every=5000 >> "$LOGS/baselines.log" 2>&1
$S report "${C[@]}" | tee "$LOGS/report.md"
