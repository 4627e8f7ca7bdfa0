#!/usr/bin/env bash
# Trains the self-play members of the default training pool (configs/pools/train_pool.json) and copies
# them into configs/pools/checkpoints/. Seeds 3 and 4: Zoo 2's drones are seeds 1 and 2, so the pool
# shares no checkpoint with an evaluation zoo (atdrone refuses a pool that does). About 10-20 minutes
# on 2 cores.
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-runs_pool}
for seed in 3 4; do
  .venv/bin/atdrone train "configs/train/pool_sp_s$seed.json" --out-dir "$out"
  cp "$out/pool_sp_s$seed/last.pt" "configs/pools/checkpoints/pool_sp_s$seed.pt"
done
