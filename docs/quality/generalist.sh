#!/bin/bash
# Issue 11 items 4 and 6: the generalist's million, one policy trained on it over the results protocol's three
# seeds, adaptation to a shifted domain from its champion, then PPO and SAC per family at the same environment
# steps (docs/results-generalist.md).
#
#   docs/quality/generalist.sh WORKSPACE [SIM2ACT]      # from the repository root; ~20 h on 2 cores
#
# 1. the iteration: explore the million (~1.4 h), train it under the results protocol's three seeds
#    (evaluate.training_seeds=3; train.steps=7000: two epochs, ~0.8 h each in bf16 where the CPU pays for it),
#    evaluate each on 228 cases x 10 episodes (~0.8 h each), the noiseless experts on the same cases;
# 2. the same command with the preset's adaptation (adapt.*: five seen tasks of the three families, 2/4/8/16
#    target-domain episodes, three seeds per point, from the champion and from scratch);
# 3. the same command with the preset's baselines: PPO and SAC from scratch per family, at the environment steps
#    the family's exploration took (255k-456k: ~15 h for SAC on robosuite, ~0.5-2 h per PPO; started longest first);
# 4. `sim2act report`: per family and split, the seeds pooled, the baselines and the adaptation curves.
# Every step is resumable or cached: running the script again skips what finished and resumes what was cut (an
# explore or evaluation unit, a training from its last checkpoint, an RL agent from its last). Logs: WORKSPACE-logs/.
set -euo pipefail
# this checkout's code, also where SIM2ACT is another checkout's install (an editable install imports its own tree)
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
W=${1:?usage: generalist.sh WORKSPACE [SIM2ACT]}
W=${W%/}
S=${2:-sim2act}
C=(--preset generalist --set render.mesh_detail=0.1 --set train.steps=7000 --set evaluate.training_seeds=3
   --workspace "$W")
LOGS=$W-logs
mkdir -p "$LOGS"
trap 'echo "generalist.sh: a step failed; its log is the newest in $LOGS/" >&2' ERR

$S run "${C[@]}" --set 'baselines.agents=[expert]' --set 'adapt.episodes_per_task=[]' >> "$LOGS/iteration.log" 2>&1
$S run "${C[@]}" --set 'baselines.agents=[expert]' >> "$LOGS/adapt.log" 2>&1
# a SAC step costs ~120 ms of a core (docs/bench-rl.md): a checkpoint every 5,000 steps (10 minutes, its ~2 GB replay
# written in seconds) rather than 25,000 (50 minutes lost to a kill or a session's end); not part of the agents' keys
# an RL agent's worker keeps every scene it opens (44 tasks a family; a scene made again draws the same frames, only
# slower), as generalist-baselines.sh and generalist-sac.sh do
SIM2ACT_SCENES_PER_WORKER=${SIM2ACT_SCENES_PER_WORKER:-64} \
  $S run "${C[@]}" --set baselines.checkpoint_every=5000 >> "$LOGS/baselines.log" 2>&1
$S report "${C[@]}" | tee "$LOGS/report.md"
