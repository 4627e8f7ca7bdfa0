#!/usr/bin/env bash
# Trains the drones of Zoo 4 (configs/zoos/zoo4.json: partners not made by the self-play recipe) and
# the validation zoo's trained drones (configs/zoos/validation.json: self-play seeds 5 and 6, which no
# test zoo or training pool uses) into configs/zoos/checkpoints/. About 30-45 minutes on 2 cores.
set -euo pipefail
cd "$(dirname "$0")/.."
exec benchmarks/train_partners.sh configs/zoos/checkpoints \
  configs/train/val_sp_s5.json configs/train/val_sp_s6.json \
  configs/train/zoo4_mappo.json configs/train/zoo4_wide.json configs/train/zoo4_entropy.json \
  configs/train/zoo4_own_credit.json configs/train/zoo4_br_greedy.json
