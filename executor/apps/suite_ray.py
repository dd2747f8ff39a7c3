"""`palletpilot test SUITE --executor ray`: every run of a suite as a Ray task, on a local Ray instance or
an existing cluster (`--ray-address ray://HOST:10001`, `auto`, or a GCS address `HOST:6379`).

Ray is optional (`pip install 'palletpilot[cluster]'`); without it `--executor ray` is one line and exit
2. Each task runs `suite_run.run_case` exactly as a local worker process does (a run is deterministic for
its seed, wherever it runs), in a temporary folder on its node, and sends back its `RunResult` and its
report folder (report.json, trajectory.csv and .png, events.jsonl, run.mcap) packed as a tar archive: the
head writes it to `REPORT/<case>/<k>/`, as the local executor does, so the nodes need no shared folder
for the outputs. The inputs travel too (`suite_inputs`): the head reads every file the runs read (suite,
missions, scenarios, maps, vehicle, forks and pallet type files) once, puts them in Ray's object store
once, and each task lays them out in its temporary folder and runs from there; the paths in its verdict
and report are written back as the head's. The segmentation model is the one each node's palletpilot
ships: a task on a node whose model differs from the head's is an `error` that says so.

Faults: a run whose worker or node dies (killed, out of memory, node lost) is submitted once more
(Ray places it on a live worker) and marked `retried`; a second death is that run's `error`. Ctrl-C
cancels the cluster's tasks; the runs that finished are returned (`RayOutcome.interrupted`), so the
summary and JUnit of those are still written.

Public API: `Executor`, `RayOutcome`, `run_on_ray`, `ray_missing`.
"""

from __future__ import annotations

import io
import logging
import tarfile
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any

from palletpilot.executor.apps.suite import RunSpec, SuiteError
from palletpilot.executor.apps.suite_inputs import Inputs, Placed, gather_inputs, model_sha256
from palletpilot.executor.apps.suite_run import RunResult, run_case

INSTALL_HINT = "pip install 'palletpilot[cluster]'"


class Executor(str, Enum):
    """Where the runs of a suite run."""

    LOCAL = "local"  # worker processes on this machine (`--jobs` of them)
    RAY = "ray"  # Ray tasks, on a local Ray instance or a cluster (`--ray-address`)


@dataclass
class RayOutcome:
    """The runs that finished, in the suite's order, how many ran at a time, and whether Ctrl-C stopped
    the campaign."""

    results: list[RunResult]
    jobs: int
    interrupted: bool = False


def ray_missing() -> str | None:
    """The one-line reason `--executor ray` cannot run here, or None when Ray is importable."""
    try:
        import ray  # noqa: F401
    except ImportError:
        return f"--executor ray: the ray package is not installed ({INSTALL_HINT})"
    return None


def _pack(folder: Path) -> bytes:
    """A run's report folder as an uncompressed tar archive (MCAP and PNG are compressed already)."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for path in sorted(folder.rglob("*")):
            if path.is_file():
                tar.add(path, arcname=str(path.relative_to(folder)), recursive=False)
    return buf.getvalue()


def _unpack(data: bytes, folder: Path) -> None:
    """Write a `_pack` archive into `folder` (regular files only, never outside it)."""
    folder.mkdir(parents=True, exist_ok=True)
    with tarfile.open(fileobj=io.BytesIO(data), mode="r") as tar:
        tar.extractall(folder, filter="data")


RESTORED_SUFFIXES = (".json", ".jsonl")
"""Report files whose text names input files: their worker paths are written back as the head's."""


def run_remote(spec: RunSpec, inputs: Inputs | None = None) -> tuple[dict[str, Any], bytes]:
    """One run on a Ray worker: its `RunResult` as JSON and its report folder packed (`b""` when none).

    With `inputs`, the run reads them from a copy in its temporary folder, not from the head's paths."""
    with tempfile.TemporaryDirectory(prefix="palletpilot-run-") as tmp:
        out = Path(tmp) / "out"
        if inputs is None:
            res = run_case(spec, out)
        elif (mine := model_sha256()) != inputs.model_sha256:
            reason = (
                f"internal error: this node's segmentation model (sha256 {mine[:12]}) is not the head's "
                f"({inputs.model_sha256[:12]}): install the same palletpilot on every node"
            )
            res = RunResult(spec.label, spec.case, spec.index, "error", False, reason, [reason], drawn=spec.drawn)
        else:
            placed = inputs.materialise(Path(tmp) / "in")
            res = _restored(run_case(placed.spec(spec), out), placed)
        folder = out / spec.case / str(spec.index)
        return res.to_json(), _pack(folder) if folder.is_dir() else b""


def _restored(res: RunResult, placed: Placed) -> RunResult:
    """A run's verdict and its report's texts with the head's paths instead of the worker's copy's."""
    res.reason = None if res.reason is None else placed.restore(res.reason)
    res.problems = [placed.restore(p) for p in res.problems]
    if res.report_dir is not None:
        for path in Path(res.report_dir).rglob("*"):
            if path.suffix in RESTORED_SUFFIXES and path.is_file():
                text = path.read_text()
                if (back := placed.restore(text)) != text:
                    path.write_text(back)
    return res


def _received(doc: dict[str, Any], data: bytes, report: Path, retried: bool) -> RunResult:
    res = RunResult(**doc)
    if res.report_dir is not None:
        folder = report / res.case / str(res.index)
        _unpack(data, folder)
        res.report_dir = str(folder)
    res.retried = retried
    return res


def _error(spec: RunSpec, what: str, exc: Exception, retried: bool) -> RunResult:
    """A run that gave no result: an `error` naming `what` happened and the exception's first line."""
    first = (str(exc).strip().splitlines() or [""])[0]
    reason = f"internal error: {what}: {type(exc).__name__}: {first}"
    res = RunResult(spec.label, spec.case, spec.index, "error", False, reason, [reason], drawn=spec.drawn)
    res.retried = retried
    return res


def run_on_ray(
    specs: list[RunSpec],
    report: Path,
    address: str | None,
    jobs: int | None,
    progress: Callable[[RunResult, int], None],
    inputs: Inputs | None = None,
) -> RayOutcome:
    """Run `specs` as Ray tasks, at most `jobs` at a time (None: as many as the cluster has CPUs), reports
    under `report`; `progress(result, done)` as each finishes. The tasks read `inputs` (default: gathered
    from `specs` now), never the head's folders. Raises `SuiteError` (one line) when Ray is missing, the
    inputs are too large or the cluster cannot be reached."""
    missing = ray_missing()
    if missing:
        raise SuiteError(missing)
    import ray
    from ray.exceptions import RayError, RayTaskError

    inputs = inputs if inputs is not None else gather_inputs(specs)
    started = not ray.is_initialized()
    if started:
        try:
            ray.init(address=address, include_dashboard=False, logging_level=logging.ERROR, log_to_driver=False)
        except Exception as exc:  # ConnectionError, ValueError for a bad address: the user's input
            raise SuiteError(f"--ray-address {address}: cannot reach the Ray cluster: {exc}") from None
    task = ray.remote(num_cpus=1, max_retries=0)(run_remote)
    shared = ray.put(inputs)  # once in the object store; each node fetches it once
    limit = jobs or max(1, int(ray.cluster_resources().get("CPU", 1)))
    waiting = list(enumerate(specs))
    running: dict[Any, tuple[int, bool]] = {}  # ref -> (index, already retried)
    results: dict[int, RunResult] = {}
    interrupted = False
    try:
        while waiting or running:
            while waiting and len(running) < limit:
                k, spec = waiting.pop(0)
                running[task.remote(spec, shared)] = (k, False)
            (ref,), _ = ray.wait(list(running), num_returns=1)
            k, retried = running.pop(ref)
            try:
                doc, data = ray.get(ref)
            except RayError as exc:
                # Ray itself failed the task (its worker or node died, or an argument could not be fetched:
                # a RayTaskError whose cause is a RayError, such as OwnerDiedError): once more, elsewhere.
                # A task that raised (run_case never does) is a bug, not retried.
                system = not isinstance(exc, RayTaskError) or isinstance(exc.cause, RayError)
                if system and not retried:
                    running[task.remote(specs[k], shared)] = (k, True)
                    continue
                what = "the run's worker died twice" if system else "the run raised"
                results[k] = _error(specs[k], what, exc, retried)
            else:
                results[k] = _received(doc, data, report, retried)
            progress(results[k], len(results))
    except KeyboardInterrupt:
        interrupted = True
        for ref in running:
            ray.cancel(ref, force=True)
    finally:
        if started:
            ray.shutdown()
    return RayOutcome([results[k] for k in sorted(results)], limit, interrupted)
