#!/usr/bin/env bash
# Trains partner drones from local train configs and copies each final checkpoint into a folder:
#   benchmarks/train_partners.sh DEST_DIR CONFIG.json [CONFIG.json ...]
# Each run lives in ${RUNS:-runs_partners}/<name>/; a finished run is not trained again and an
# interrupted one resumes from its last checkpoint, so the script can simply be run again after a
# kill. The checkpoint lands in DEST_DIR/<name>.pt (its header names the config, seed, env steps and
# last evaluation). Used by train_pool.sh (the default training pool) and train_zoos.sh (Zoo 4 and
# the validation zoo's trained drones).
set -euo pipefail
cd "$(dirname "$0")/.."
if [ $# -lt 2 ]; then
  echo "usage: $0 DEST_DIR CONFIG.json [CONFIG.json ...]" >&2
  exit 2
fi
dest=$1
shift
runs=${RUNS:-runs_partners}
mkdir -p "$dest"
for config in "$@"; do
  name=$(.venv/bin/python -c 'import json, sys; print(json.load(open(sys.argv[1]))["name"])' "$config")
  if [ -f "$dest/$name.pt" ]; then
    echo "[$name] $dest/$name.pt exists: skipped"
    continue
  fi
  if [ -d "$runs/$name" ]; then
    .venv/bin/atdrone train "$config" --out-dir "$runs" --resume
  else
    .venv/bin/atdrone train "$config" --out-dir "$runs"
  fi
  cp "$runs/$name/last.pt" "$dest/$name.pt.tmp" && mv "$dest/$name.pt.tmp" "$dest/$name.pt"
done
