"""Solver benchmark (issue 4): the same as ``torchslam bench``; see torchslam/cli/bench.py.

.venv/bin/python experiments/bench_solver.py [--cases S M L O BATCH] [--repeats N] [--quick]
"""

from torchslam.cli.bench import main

if __name__ == "__main__":
    main()
