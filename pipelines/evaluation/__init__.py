"""Evaluation: tasks and executors, benchmark suites and tables, sensitivity sweeps, the bench_* scripts."""
