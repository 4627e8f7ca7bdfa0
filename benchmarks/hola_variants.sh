#!/bin/bash
# Issue 13's HOLA-Drone V2 variants on 4p2e5o, 3 seeds each, at the report's equal budget
# (1,048,576 env steps; the last one doubles it for HOLA and SP). Resumable: run it again
# after an interruption and every phase continues where it stopped. Then rebuild the report:
#   .venv/bin/python benchmarks/hola_report.py --tasks 4p2e5o 4p3e5o --phases report
set -e
cd "$(dirname "$0")/.."
P=".venv/bin/python benchmarks/hola_report.py --tasks 4p2e5o"
run() { $P --phases train evaluate "$@"; }
run --algorithms hola --tag suc --weight SUC                # hyperedge weight: team SUC instead of return
run --algorithms hola --tag nospread --pi0-levels 1         # Pi_0 without spread: final snapshots only
run --algorithms hola --tag scratch --learner-start scratch # learners from scratch instead of the last learner
run --algorithms hola --tag sharp --eta-prior 0.1           # a sharper eta = 0 rule (prior count 0.1 instead of 1)
run --algorithms hola sp --tag 2M --env-steps 2097152       # the budget doubled, HOLA and SP alike
echo "variants done"
