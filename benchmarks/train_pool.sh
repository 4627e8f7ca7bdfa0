#!/usr/bin/env bash
# Trains the self-play members of the default training pool (configs/pools/train_pool.json) into
# configs/pools/checkpoints/. Seeds 3 and 4: Zoo 2's drones are seeds 1 and 2, so the pool shares no
# checkpoint with an evaluation zoo (atdrone refuses a pool that does). About 10-20 minutes on 2 cores.
set -euo pipefail
cd "$(dirname "$0")/.."
exec benchmarks/train_partners.sh configs/pools/checkpoints configs/train/pool_sp_s3.json configs/train/pool_sp_s4.json
