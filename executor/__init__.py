"""The mission executor and the `palletpilot` CLI (`executor.cli:main`).

So far: the CLI's map, plan and bench commands. Missions, task state machines and the runner come
with the executor issue.
"""
