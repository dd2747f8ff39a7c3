"""The mission executor's core: missions, the task machines and their behaviours, the runner and its
watchdogs, jobs, clocks, checkpoints. It sees the world through `executor.ports` only and imports no
adapter, no app and no heavy I/O library (import-linter, pyproject)."""
