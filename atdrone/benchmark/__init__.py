"""The benchmark: a grid of service experiments (methods x tasks x seeds, best responses, floors) run over
a Ray cluster as one resumable job, its report (tables, paired differences, aggregates, figures) and the
weights it keeps. See docs/benchmark.md."""
