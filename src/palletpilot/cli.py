"""The `palletpilot` console script: the executor's commands plus `palletpilot bench`.

It is the composition root, the one module above both `executor` and `bench`, so that the executor
never imports the benchmarks (which drive the executor). Signal handlers go in first, before anything
heavy loads: SIGUSR1 / SIGUSR2 (pause / resume) are never fatal, and for a run SIGINT and SIGTERM
cancel the mission (vehicle stopped, report written) even while it is still starting up.
"""

from __future__ import annotations

import sys

from palletpilot.executor.core.controls import install_signal_handlers

# Commands that drive a vehicle: a signal cancels them cleanly instead of killing the process.
_VEHICLE_COMMANDS = ("run",)
install_signal_handlers(cancel=any(arg in _VEHICLE_COMMANDS for arg in sys.argv[1:2]))

import os  # noqa: E402

# Our matrices are small (poses, point sets of thousands): a multi-threaded BLAS only oversubscribes
# the cores (measured: 11 ms SVDs of 3500 x 6 matrices under load). Set before numpy loads.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from collections.abc import Sequence  # noqa: E402

from palletpilot.bench.cli import add_parsers as add_bench_parsers  # noqa: E402
from palletpilot.executor.apps import cli as executor_cli  # noqa: E402


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of `palletpilot`; returns the exit code (executor.cli lists them)."""
    return executor_cli.main(argv, extensions=(add_bench_parsers,))


if __name__ == "__main__":
    sys.exit(main())
