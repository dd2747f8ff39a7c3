"""The input files of a suite's runs, gathered on the head and laid out again on a Ray worker, so the
nodes of a cluster need no shared folder and no copy of the suite.

`gather_inputs(specs, suite_file)` reads every file the runs read (the suite file, each mission, its map
and the map's vehicle file, each scenario file or drawn scenario's base folder references, forks,
vehicle and pallet type files), following the file names written in those YAML files (any value that
names an existing file relative to its file's folder, or an absolute one), into an `Inputs`: the bytes
by the head's absolute path. A name that names no file is left out, and the worker then refuses it as
the head would; with it go the YAML files of that folder, so the did-you-mean of the refusal is the
head's.

On the worker, `Inputs.materialise(tmp)` writes the files under `tmp/t/<head's absolute path>` (the
YAML files' absolute file names rewritten to point there) and links `tmp/c` to the head's working
folder in that tree; `Placed.spec(spec)` gives the run's spec with its paths moved there (a relative
path stays relative to `tmp/c`); `Placed.restore(text)` maps paths in messages and report texts back to
the head's, so a run's verdict and reason are the same on either executor.

The segmentation model is the one each node's palletpilot ships (`run_simulated` takes no other); the
head sends its digest and a worker whose model differs refuses the run (an `error`, never another
model's verdict).

Public API: `Inputs`, `Placed`, `gather_inputs`, `MAX_INPUT_BYTES`.
"""

from __future__ import annotations

import functools
import hashlib
import os
import re
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from palletpilot.executor.apps.suite import RunSpec, SuiteError
from palletpilot.geometry import PalletpilotError
from palletpilot.geometry.fileio import read_yaml

MAX_INPUT_BYTES = 1 << 30
"""The most input bytes a suite sends to the cluster (1 GiB): the object store holds them once."""
YAML_SUFFIXES = (".yaml", ".yml", ".json")
"""Files read as documents (`read_yaml`): the file names in them are followed and rewritten."""
_NAME_CHARS = 4096  # longer strings are no file names


@dataclass(frozen=True)
class Inputs:
    """A suite's input files by the head's absolute path, the absolute names written in its YAML files,
    the head's working folder and its segmentation model's SHA-256 (picklable; sent once per suite)."""

    files: dict[str, bytes]
    absolute_names: tuple[str, ...]
    cwd: str
    model_sha256: str

    @property
    def size(self) -> int:
        """The bytes of all files."""
        return sum(len(b) for b in self.files.values())

    def materialise(self, tmp: Path) -> Placed:
        """Write the files under `tmp` (a fresh folder on the worker) and say where they are."""
        tmp = tmp.resolve()  # restore() matches the paths a run may print resolved (/tmp -> /private/tmp)
        tree, cwd_link = tmp / "t", tmp / "c"
        names = sorted(self.absolute_names, key=len, reverse=True)
        pattern = re.compile(r"(?<![\w./-])(?:" + "|".join(re.escape(n) for n in names) + ")") if names else None
        for name, data in self.files.items():
            path = tree / name.lstrip("/")
            path.parent.mkdir(parents=True, exist_ok=True)
            if pattern is not None and path.suffix.lower() in YAML_SUFFIXES:
                data = pattern.sub(lambda m: str(tree) + m.group(0), data.decode("utf-8", "surrogateescape")).encode(
                    "utf-8", "surrogateescape"
                )
            path.write_bytes(data)
        home = tree / self.cwd.lstrip("/")
        home.mkdir(parents=True, exist_ok=True)
        cwd_link.symlink_to(home, target_is_directory=True)
        return Placed(tree, cwd_link, tuple(names))


@dataclass(frozen=True)
class Placed:
    """Where a worker laid the inputs out: `tree` mirrors the head's absolute paths, `cwd` (a link into
    it) stands for the head's working folder."""

    tree: Path
    cwd: Path
    absolute_names: tuple[str, ...]

    def path(self, p: Path) -> Path:
        """A head path as the worker reads it."""
        return self.tree / str(p).lstrip("/") if p.is_absolute() else self.cwd / p

    def spec(self, spec: RunSpec) -> RunSpec:
        """`spec` with its files read from the worker's copy."""
        return replace(
            spec,
            mission=self.path(spec.mission),
            scenario_path=None if spec.scenario_path is None else self.path(spec.scenario_path),
            scenario_folder=None if spec.scenario_folder is None else self.path(spec.scenario_folder),
            scenario_doc=None if spec.scenario_doc is None else self._doc(spec.scenario_doc),
        )

    def _doc(self, value: Any) -> Any:
        """A drawn scenario with its absolute file names moved to the worker's copy."""
        if isinstance(value, dict):
            return {k: self._doc(v) for k, v in value.items()}
        if isinstance(value, list):
            return [self._doc(v) for v in value]
        if isinstance(value, str) and value in self.absolute_names:
            return str(self.tree) + value
        return value

    def restore(self, text: str) -> str:
        """`text` with the worker's paths written as the head's (`tmp/c/x` -> `x`, `tmp/t/a/b` -> `/a/b`)."""
        return text.replace(f"{self.cwd}/", "").replace(str(self.cwd), ".").replace(str(self.tree), "")


@functools.cache
def model_sha256() -> str:
    """The SHA-256 of the segmentation model this palletpilot ships (read once per process)."""
    from palletpilot.perception.segmentation import DEFAULT_MODEL

    return hashlib.sha256(Path(DEFAULT_MODEL).read_bytes()).hexdigest()


def _strings(value: Any) -> Iterator[str]:
    """Every string in a parsed YAML document that may be a file name."""
    if isinstance(value, dict):
        for v in value.values():
            yield from _strings(v)
    elif isinstance(value, list):
        for v in value:
            yield from _strings(v)
    elif isinstance(value, str) and 0 < len(value) < _NAME_CHARS and ("." in value or "/" in value):
        yield value


class _Gatherer:
    """Collects files and the files their YAML names, each once."""

    def __init__(self) -> None:
        self.files: dict[str, bytes] = {}
        self.followed: set[str] = set()
        self.absolute_names: set[str] = set()

    def add(self, path: Path, follow: bool = True) -> None:
        """Add `path` (when it is a file) and, for YAML (or JSON) with `follow`, the files it names."""
        key = os.path.abspath(path)
        if key not in self.files:
            if not os.path.isfile(key):
                return
            try:
                self.files[key] = Path(key).read_bytes()
            except OSError:
                return  # unreadable: the worker refuses it, as the head would
        if follow and key not in self.followed and Path(key).suffix.lower() in YAML_SUFFIXES:
            self.followed.add(key)
            try:
                doc = read_yaml(key)
            except PalletpilotError:
                return  # the run refuses it, from the same bytes
            self.names(doc, Path(path).parent)

    def names(self, doc: Any, folder: Path) -> None:
        """Add the files named in `doc` (relative to `folder`); a missing YAML's folder brings its YAML files."""
        for name in _strings(doc):
            target = Path(name) if os.path.isabs(name) else folder / name
            if os.path.isfile(target):
                if os.path.isabs(name):
                    self.absolute_names.add(name)
                self.add(target)
            elif target.suffix.lower() in YAML_SUFFIXES and target.parent.is_dir():
                for sibling in sorted(target.parent.glob("*.y*ml")):  # what a did-you-mean offers
                    self.add(sibling, follow=False)
                if os.path.isabs(name):
                    self.absolute_names.add(name)


def gather_inputs(specs: list[RunSpec], suite_file: Path | None = None) -> Inputs:
    """Every file the runs of `specs` read, by absolute path; raises `SuiteError` past `MAX_INPUT_BYTES`."""
    g = _Gatherer()
    if suite_file is not None:
        g.add(suite_file, follow=False)  # the runs take their cases from the specs; sent for the record
    for spec in specs:
        for path in (spec.mission, spec.scenario_path):
            if path is not None:
                if path.is_absolute():
                    g.absolute_names.add(str(path))
                g.add(path)
        if spec.scenario_doc is not None:
            g.names(spec.scenario_doc, spec.scenario_folder or Path("."))
    inputs = Inputs(g.files, tuple(sorted(g.absolute_names)), os.getcwd(), model_sha256())
    if inputs.size > MAX_INPUT_BYTES:
        raise SuiteError(
            f"the suite's input files are {inputs.size / 2**20:.1f} MiB, more than the "
            f"{MAX_INPUT_BYTES / 2**20:.1f} MiB sent to a cluster"
        )
    return inputs
