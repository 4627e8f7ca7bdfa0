#!/bin/bash
# Issue 22's powered test of the paper's claim on 4p2e5o: HOLA-Drone V2, w/o g, SP and
# FCP-style Pi_0-only (a learner trained against a frozen pool of 2 self-play seeds x 2 skill
# levels, HOLA's Pi_0 recipe), 8 seeds each at 1,048,576 env steps per run, every final
# learner evaluated with 2,000 episodes on each of Zoos 1-4, paired differences against SP
# and w/o g. Many hours of the 2-core machine (measured: a HOLA generation after Pi_0 takes
# 80-110 s on the idle machine, 300-770 s beside a test suite; the 32 runs about 8 hours idle, not
# the 4-5 first guessed): run it in chunks, each run of this script continues where the last
# stopped (finished runs and evaluations are kept). Its runs use 2 PPO epochs, the default when the
# study was designed (--ppo-epochs 2; the default is 4 since).
#
# Every run trains with the code of commit 9f2ab7f (issue 26's training kernels), so edits made while the
# study runs for hours cannot reach its runs: the script runs that commit from a git worktree beside this
# one (../hola_tree, made if missing; HOLA_POWER_TREE names another), with this checkout's .venv, and
# writes into this checkout's reports/ and benchmarks/results/hola_power/; after each run the
# finished runs' kept files go to benchmarks/results/hola_power/archive/ (commit it between chunks:
# benchmarks/hola_archive.py restores them into a fresh checkout's reports/). The report phase runs this
# checkout's code: it only reads what the runs and evaluations wrote.
#   nohup nice -n 19 benchmarks/hola_power.sh >> reports/hola_power.log 2>&1 &
set -e
cd "$(dirname "$0")/.."
main=$PWD
tree=${HOLA_POWER_TREE:-$main/../hola_tree}
[ -d "$tree" ] || git worktree add --detach "$tree" 9f2ab7f
[ "$(git -C "$tree" rev-parse --short=7 HEAD)" = 9f2ab7f ] || { echo "$tree is not at 9f2ab7f" >&2; exit 2; }
mkdir -p reports benchmarks/results/hola_power
for p in .venv reports benchmarks/results/hola_power; do [ -e "$tree/$p" ] || ln -s "$main/$p" "$tree/$p"; done
# the study's arguments to hola_report.py, shared by its runs (pinned tree) and its report (this checkout)
study_args=(--tasks 4p2e5o --algorithms hola hola_no_g sp fcp --episodes 2000 --zoos zoo1 zoo2 zoo3 zoo4
  --title "HOLA-Drone V2 with the power to decide (issue 22)" --out reports/hola_power
  --results benchmarks/results/hola_power)
study() {  # hola_report.py of the pinned tree, with this study's arguments and any given
  (cd "$tree" && PYTHONPATH=$tree .venv/bin/python benchmarks/hola_report.py "${study_args[@]}" \
    --fcp-seeds 2 --fcp-levels 2 --ppo-epochs 2 --references sp hola_no_g --resume "$@")
}
archive() {  # the finished runs and evaluations into the committed archive (reports/ may not survive a session)
  PYTHONPATH=$main .venv/bin/python benchmarks/hola_archive.py "$1" --out reports/hola_power \
    --archive benchmarks/results/hola_power/archive
}
archive restore
# one run at a time, archived after each: a chunk's finished runs outlive the machine it ran on
for seed in 0 1 2 3 4 5 6 7; do
  for alg in hola hola_no_g sp fcp; do
    # a finished run (restored from the archive or trained before) is skipped without starting Ray
    [ -e "reports/hola_power/runs/4p2e5o-$alg-s$seed/population.csv" ] && continue
    study --seeds "$seed" --algorithms "$alg" --phases train
    archive save
  done
done
for seed in 0 1 2 3 4 5 6 7; do study --seeds "$seed" --phases evaluate; archive save; done
# the report with this checkout's code (it only reads the runs and evaluations): rho against its nulls, paired
# differences against SP, SP at HOLA's learner samples, w/o g and the Pi_0-only FCP
PYTHONPATH=$main .venv/bin/python benchmarks/hola_report.py "${study_args[@]}" \
  --references sp sp@samples hola_no_g fcp --seeds 0 1 2 3 4 5 6 7 --phases report
