"""YAML files validated by pydantic models, with errors as one line per problem.

Every package loads its files (maps, vehicle, forks, scenarios, missions) through `load_yaml_model`,
so every bad file is reported the same way: `path: nodes[3].yaw_deg: Input should be a valid number`.
Every schema derives from `FileModel` (unknown keys and NaN / infinities are errors); `read_text`
refuses files that are too large or not UTF-8, `read_yaml` anchor bombs and deep nesting, and
`parse_json` the NaN and Infinity that Python's json would accept.
It lives in `geometry` because that is the one package all others may import.

`bundled_path("missions", "warehouse.yaml")` is a file shipped inside the installed package (the
example missions, the ONNX model), found through `importlib.resources`, never relative to a source file.

Every output file is written the one way, `write_atomic` (temporary file in the same folder, fsync,
rename, fsync of the folder, mode 0666 minus the umask as `open()` gives): a reader sees the old file
or the new one, never a truncated one, and a failed write (full disk, no permission) leaves the old
file and raises `OutputError` with one line.
JSON output is strict RFC 8259 (`strict_json`, `dumps_json`): NaN and infinities become `null`.
Dimensions in files: `FileNumber` (a number, never a string or a boolean), `check_ranges` / `range_error`
(a value outside its plausible range, named with the range).
"""

from __future__ import annotations

import atexit
import contextlib
import json
import math
import os
import tempfile
import typing
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo
from pydantic_core import PydanticCustomError

from palletpilot.geometry.errors import OutputError, PalletpilotError, did_you_mean

M = TypeVar("M", bound=BaseModel)

MAX_TEXT_BYTES = 256 * 2**20
"""The largest text input read (bytes): a 100,000-node map is about 20 MB."""
MAX_ITEMS = 10_000_000
"""The most values (scalars, lists and mappings) a YAML or JSON file may expand into."""
MAX_DEPTH = 100
"""The deepest nesting of lists and mappings a YAML or JSON file may have."""

_SafeLoader: Any = getattr(yaml, "CSafeLoader", yaml.SafeLoader)

# Keeps files extracted by `importlib.resources.as_file` (a zipped install) until the process ends.
_RESOURCES = contextlib.ExitStack()
atexit.register(_RESOURCES.close)


def bundled_path(*parts: str) -> Path:
    """A file or folder shipped in the `palletpilot` package, e.g. `bundled_path("missions", "forks.yaml")`."""
    ref = resources.files("palletpilot").joinpath(*parts)
    return Path(_RESOURCES.enter_context(resources.as_file(ref)))


class FileModel(BaseModel):
    """Base of every file schema: unknown keys are errors, and so are NaN and infinities.

    A subclass adds to the config (`model_config = ConfigDict(frozen=True)`); pydantic merges it.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


FileNumber = Annotated[float, Field(strict=True)]
"""A number in a file (an int or a float; finite by `FileModel`), never a string or a boolean."""


def range_error(value: float, lo: float, hi: float, what: str) -> PydanticCustomError:
    """The error for a dimension outside its range: names the range and the value."""
    return PydanticCustomError("out_of_range", f"{value:g} m is outside {lo:g}..{hi:g} m ({what})")


def check_ranges(
    value: float | tuple[float, ...], info: ValidationInfo, ranges: dict[str, tuple[float, float, str]]
) -> None:
    """Raise `range_error` when `value` (or an element of it) lies outside `ranges[field]`."""
    assert info.field_name is not None
    lo, hi, what = ranges[info.field_name]
    for v in value if isinstance(value, tuple) else (value,):
        if not lo <= v <= hi:
            raise range_error(v, lo, hi, what)


def read_text(
    path: str | Path, error: type[PalletpilotError] = PalletpilotError, max_bytes: int = MAX_TEXT_BYTES
) -> str:
    """A UTF-8 text file (a byte-order mark is allowed); unreadable, oversized or not UTF-8: `error`, one line."""
    path = Path(path)
    if path.exists() and not path.is_file() and not path.is_dir():  # a FIFO or device would block or never end
        raise error(f"{path}: cannot read: not a regular file")
    try:
        with path.open("rb") as f:
            data = f.read(max_bytes + 1)
    except OSError as exc:
        raise error(f"{path}: cannot read: {exc.strerror or exc}") from None
    if len(data) > max_bytes:
        raise error(f"{path}: too large: more than {max_bytes / 2**20:.0f} MiB (limit {max_bytes} bytes)")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise error(
            f"{path}: not UTF-8 text: byte 0x{data[exc.start]:02x} at offset {exc.start} (line {line}); "
            "save the file as UTF-8"
        ) from None


def _yaml_line(exc: yaml.YAMLError, text: str) -> str:
    """`line N: what`, naming a tab as a tab (YAML's own message for one says nothing of tabs)."""
    mark = getattr(exc, "problem_mark", None)
    if mark is None:
        return str(getattr(exc, "problem", None) or exc)
    lines = text.splitlines()
    line = lines[mark.line] if mark.line < len(lines) else ""
    if (mark.column < len(line) and line[mark.column] == "\t") or "\t" in line[: len(line) - len(line.lstrip())]:
        return f"line {mark.line + 1}: a tab character (YAML indents with spaces only; replace the tab by spaces)"
    return f"line {mark.line + 1}: {getattr(exc, 'problem', None) or exc}"


def read_yaml(path: str | Path, error: type[PalletpilotError] = PalletpilotError) -> object:
    """Parse a YAML file (JSON for a `.json` file); every problem raises `error` with one line naming the file.

    Problems: unreadable, larger than `MAX_TEXT_BYTES`, not UTF-8, a syntax error, a Python tag
    (`!!python/...`: never executed), or more than `MAX_ITEMS` values once anchors are expanded.
    YAML goes through libyaml (`CSafeLoader`) where PyYAML has it, about 5x faster than pure Python.
    """
    path = Path(path)
    text = read_text(path, error)
    if path.suffix.lower() == ".json":
        data = parse_json(text, str(path), error)
    else:
        try:
            data = yaml.load(text, Loader=_SafeLoader)  # a safe loader: never builds Python objects
        except yaml.YAMLError as exc:
            if "maximum nesting depth" in str(exc):  # the limit libyaml itself has in recent PyYAML wheels
                raise error(f"{path}: nested deeper than {MAX_DEPTH} levels") from None
            raise error(f"{path}: not valid YAML: {_yaml_line(exc, text)}") from None
        except RecursionError:
            raise error(f"{path}: not valid YAML: nested too deeply") from None
    check_size(data, str(path), error)
    return data


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not a number in JSON (RFC 8259)")


def parse_json(text: str, where: str, error: type[PalletpilotError] = PalletpilotError) -> object:
    """Strict JSON (RFC 8259: no NaN or Infinity); a syntax error raises `error` naming `where` and the line."""
    try:
        return json.loads(text, parse_constant=_reject_constant)
    except json.JSONDecodeError as exc:
        raise error(f"{where}: not valid JSON: line {exc.lineno} column {exc.colno}: {exc.msg}") from None
    except ValueError as exc:
        raise error(f"{where}: not valid JSON: {exc}") from None
    except RecursionError:
        raise error(f"{where}: not valid JSON: nested too deeply") from None


def check_size(data: object, where: str, error: type[PalletpilotError] = PalletpilotError) -> None:
    """Refuse parsed data with more than `MAX_ITEMS` values or nested deeper than `MAX_DEPTH`.

    YAML anchors make a small file expand into a huge document ("billion laughs"); the count
    follows every reference, and stops as soon as the limit is passed.
    """
    if not isinstance(data, (dict, list)):
        return
    count = 1
    stack: list[tuple[object, int]] = [(data, 0)]
    while stack:
        item, depth = stack.pop()
        values = list(item.values()) if isinstance(item, dict) else item
        assert isinstance(values, list)
        count += len(values)
        if count > MAX_ITEMS:
            raise error(f"{where}: too large: more than {MAX_ITEMS} values (after expanding YAML anchors)")
        if depth >= MAX_DEPTH:
            raise error(f"{where}: nested deeper than {MAX_DEPTH} levels")
        stack.extend((v, depth + 1) for v in values if isinstance(v, (dict, list)))


def _models_in(annotation: Any) -> list[Any]:
    """The types an annotation may hold, unwrapped from Optional, Union, Annotated, list and dict."""
    args = typing.get_args(annotation)
    if not args:
        return [annotation]
    if typing.get_origin(annotation) is typing.Annotated:
        return _models_in(args[0])
    if typing.get_origin(annotation) is dict:
        return _models_in(args[-1])
    return [t for a in args for t in _models_in(a)]


def _keys_at(model: Any, loc: tuple[Any, ...]) -> list[str]:
    """The keys the schema allows where `loc` (a pydantic error's location, less the bad key) points."""
    current = [model]
    for part in loc:
        models = [m for m in current if isinstance(m, type) and issubclass(m, BaseModel)]
        if isinstance(part, int) or not models:
            current = [t for c in current for t in _models_in(c)]
            continue
        fields = [m.model_fields[part] for m in models if part in m.model_fields]
        if fields:
            current = [t for f in fields for t in _models_in(f.annotation)]
        else:  # a discriminated union's tag (`tasks[2].charge`): the member whose literal field is `part`
            current = [m for m in models if any(part in typing.get_args(f.annotation) for f in m.model_fields.values())]
    return [k for m in current if isinstance(m, type) and issubclass(m, BaseModel) for k in m.model_fields]


def error_message(err: Any, model: Any) -> str:
    """A pydantic error's message (`ValidationError.errors()`), with a "did you mean" for a mistyped key or tag."""
    if err["type"] == "union_tag_invalid":
        ctx = err["ctx"]
        known = [t.strip(" '") for t in ctx["expected_tags"].split(",")]
        hint = did_you_mean(str(ctx["tag"]), known)
        return f"{ctx['discriminator'].strip(chr(39))} '{ctx['tag']}' is unknown{hint}; known: {', '.join(known)}"
    if err["type"] == "extra_forbidden" and model is not None and err["loc"]:
        key = str(err["loc"][-1])
        return f"{err['msg']}{did_you_mean(key, _keys_at(model, tuple(err['loc'][:-1])))}"
    return str(err["msg"])


def validation_lines(prefix: str, exc: ValidationError, model: Any = None) -> list[str]:
    """One line per pydantic error: `prefix: nodes[3].yaw_deg: Input should be a valid number`.

    With the `model` that raised it, a mistyped key gets `(did you mean 'name'?)`; a
    mistyped tag of a tagged union (a task's `type`) names the close one and the known ones.
    """
    lines = []
    for err in exc.errors():
        loc = ""
        for part in err["loc"]:
            loc += f"[{part}]" if isinstance(part, int) else (f".{part}" if loc else str(part))
        lines.append(f"{prefix}: {loc or 'file'}: {error_message(err, model)}")
    return lines


def validate_model(data: object, model: type[M], where: str, error: type[PalletpilotError] = PalletpilotError) -> M:
    """Validate already-parsed data against `model`; every problem becomes one line of `error.problems`."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        lines = validation_lines(where, exc, model)
        raise error(lines[0] if len(lines) == 1 else f"{where}: {len(lines)} problems", lines) from None


def load_yaml_model(path: str | Path, model: type[M], error: type[PalletpilotError] = PalletpilotError) -> M:
    """Read a YAML (or `.json`) file and validate it against `model`, raising `error` (one line per problem)."""
    return validate_model(read_yaml(path, error), model, str(path), error)


def current_umask() -> int:
    """The process's file mode creation mask, read without changing it where Linux allows (/proc)."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    mask = os.umask(0o022)  # elsewhere: set and restore (there is no read-only call)
    os.umask(mask)
    return mask


def write_atomic(path: str | Path, data: bytes | str) -> Path:
    """Replace `path` with `data` atomically (temp file, fsync, rename); raises `OutputError` on failure.

    The file gets the mode any `open()` would give it, 0666 minus the user's umask (`-rw-r--r--` under
    umask 022), not mkstemp's private 0600, so a CI server or a colleague can read the reports.
    """
    path = Path(path)
    payload = data.encode() if isinstance(data, str) else data
    tmp: str | None = None
    if path.exists() and not path.is_file():  # never rename over a folder or a device (/dev/full)
        raise OutputError(f"{path}: cannot write: {'a folder' if path.is_dir() else 'not a regular file'}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        with contextlib.suppress(OSError, AttributeError):  # mkstemp gives 0600; os.fchmod is POSIX only
            os.fchmod(fd, 0o666 & ~current_umask())
        with os.fdopen(fd, "wb") as f:
            f.write(payload)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        tmp = None
        _fsync_dir(path.parent)
    except OSError as exc:
        raise OutputError(f"{path}: cannot write: {exc.strerror or exc}") from None
    finally:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
    return path


def output_problems(path: str | Path, suffixes: tuple[str, ...] = (), folder: bool = False) -> list[str]:
    """What stops `path` from being written, checked before any work starts; [] when it can be.

    A file output must not be a folder or a device, must end in one of `suffixes` (when given, e.g.
    `(".png",)`), and its nearest existing parent must be a writable folder (missing folders are
    created). `folder=True`: `path` is a report folder, which may exist as a folder.
    """
    path = Path(path)
    if not str(path):
        return ["empty path"]
    if folder:
        if path.exists() and not path.is_dir():
            return [f"{path}: not a folder"]
    else:
        if path.is_dir():
            return [f"{path}: is a folder; give a file name"]
        if path.exists() and not path.is_file():
            return [f"{path}: not a regular file (a device or socket); give a file name"]
        if suffixes and path.suffix.lower() not in suffixes:
            return [f"{path}: must end in {' or '.join(suffixes)}"]
    parent = path if folder else path.parent
    parent = Path(os.path.abspath(parent))
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        return [f"{path}: {parent} is a file, not a folder"]
    target = path if folder and path.exists() else parent
    if not os.access(target, os.W_OK | os.X_OK):
        return [f"{path}: cannot write: {target} is not writable (permission or a read-only file system)"]
    if not folder and path.exists() and not os.access(path, os.W_OK):
        # rename replaces even a read-only file; say so rather than silently overwriting it
        return [f"{path}: cannot write: the file is read-only"]
    return []


def _fsync_dir(folder: Path) -> None:
    """Make a rename in `folder` durable (a no-op where directories cannot be opened, e.g. Windows)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def strict_json(obj: object) -> object:
    """`obj` with NaN and infinities as None and numpy values as plain Python (RFC 8259 has no NaN)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): strict_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [strict_json(v) for v in obj]
    if hasattr(obj, "tolist"):  # numpy arrays and scalars
        return strict_json(obj.tolist())
    if obj is None or isinstance(obj, (str, int, bool)):
        return obj
    return str(obj)


def dumps_json(obj: object, indent: int | None = None) -> str:
    """Strict JSON text of `obj` (non-finite numbers as null)."""
    return json.dumps(strict_json(obj), indent=indent, allow_nan=False)


def write_json(path: str | Path, obj: object) -> Path:
    """Write `obj` as strict, indented JSON, atomically (`write_atomic`)."""
    return write_atomic(path, dumps_json(obj, indent=2) + "\n")
