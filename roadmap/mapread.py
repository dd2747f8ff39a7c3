"""Reading map files fast: a 100,000-node map (20 MB of YAML) parses in a few seconds.

`read_map_data(path)` returns the parsed document of a map file, exactly what
`geometry.fileio.read_yaml` returns, with every problem reported the same way:

- `.json`: `read_yaml` itself (strict JSON: C speed already).
- YAML: libyaml's event stream built straight into dicts and lists, with the plain scalars resolved
  as PyYAML's safe loader resolves them (and each distinct one constructed once). That skips
  PyYAML's node graph and its Python constructor, about 3x faster. Anything unusual (anchors and
  aliases, tags, merge keys, timestamps, complex keys, several documents, a syntax error) goes back
  to `read_yaml`, so errors, anchor bombs and rare types behave exactly as for every other file.

Python's cyclic garbage collector walks every live object each time enough new containers pile up,
which makes building hundreds of thousands of dicts quadratic; `gc_paused()` holds it off while a
map loads (nothing built there is cyclic).

`map_vehicle_file` needs the map only for its `vehicle` key: a map read before (unchanged: same
file, size and modification time) answers from memory; otherwise the document parsed for it is
kept for the load that follows. Either way `palletpilot map check` parses a large map once.
"""

from __future__ import annotations

import gc
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import yaml
from yaml.events import (
    DocumentEndEvent,
    MappingEndEvent,
    MappingStartEvent,
    ScalarEvent,
    SequenceEndEvent,
    SequenceStartEvent,
    StreamEndEvent,
    StreamStartEvent,
)
from yaml.nodes import ScalarNode

from palletpilot.geometry.fileio import MAX_DEPTH, MAX_ITEMS, check_size, read_text, read_yaml
from palletpilot.roadmap.errors import RoadmapError

_LOADER: Any = getattr(yaml, "CSafeLoader", None)  # libyaml; without it, PyYAML's own loader
_RESOLVERS = yaml.resolver.Resolver.yaml_implicit_resolvers
_TAG = "tag:yaml.org,2002:"

_kept: dict[tuple[str, int, int, int, int], object] = {}  # at most one parsed document
_vehicles: dict[tuple[str, int, int, int, int], object] = {}  # each map read's `vehicle` value


class _UnusualYamlError(Exception):
    """The document needs PyYAML's full loader."""


@contextmanager
def gc_paused() -> Iterator[None]:
    """Hold off the cyclic garbage collector for a scope (it is switched back on as it was)."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


def _identity(path: Path) -> tuple[str, int, int, int, int] | None:
    try:
        st = path.stat()
    except OSError:
        return None
    return (os.path.abspath(path), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


def read_map_data(path: str | Path, keep: bool = False) -> object:
    """The parsed document of a map file (YAML, or JSON for `.json`); problems raise `RoadmapError`, one line.

    `keep=True` keeps the document for the next call on the same unchanged file.
    """
    path = Path(path)
    key = _identity(path)
    if key is not None and key in _kept:
        return _kept[key] if keep else _kept.pop(key)
    _kept.clear()
    with gc_paused():
        data = _read(path)
    if key is not None:
        if len(_vehicles) > 64:
            _vehicles.clear()
        _vehicles[key] = data.get("vehicle") if isinstance(data, dict) else None
        if keep:
            _kept[key] = data
    return data


def map_vehicle_entry(path: str | Path) -> object:
    """The map's `vehicle` value as written (None when it has none), parsing the file only when it was
    not read before unchanged; the document parsed here is kept for the load that follows."""
    key = _identity(Path(path))
    if key is not None and key in _vehicles:
        return _vehicles[key]
    data = read_map_data(path, keep=True)
    return data.get("vehicle") if isinstance(data, dict) else None


def _read(path: Path) -> object:
    if path.suffix.lower() == ".json" or _LOADER is None:
        return read_yaml(path, RoadmapError)
    text = read_text(path, RoadmapError)
    try:
        data, values, depth = fast_yaml(text)
    except (_UnusualYamlError, yaml.YAMLError, RecursionError):
        return read_yaml(path, RoadmapError)  # the full loader: its data, or its one-line error
    if values + 1 > MAX_ITEMS or depth >= MAX_DEPTH:
        check_size(data, str(path), RoadmapError)  # raises the one-line message every file gets
    return data


def fast_yaml(text: str) -> tuple[object, int, int]:
    """YAML text to Python data as `yaml.load(text, CSafeLoader)` builds it, for documents without
    anchors, aliases, tags, merge keys, timestamps or complex keys (`_UnusualYamlError` otherwise).

    Also returns how many values the containers hold and how deep they nest (the root container
    is at depth 0), the figures `fileio.check_size` limits.
    """
    loader = _LOADER(text)
    scalars: dict[str, object] = {}

    def plain(value: str) -> object:
        """A plain scalar resolved and constructed as the safe loader does it."""
        tag = _TAG + "str"
        for candidate, regexp in _RESOLVERS.get(value[0] if value else "", []):
            if regexp.match(value):
                tag = candidate
                break
        kind = tag[len(_TAG) :]
        if kind == "str":
            return value
        if kind == "null":
            return None
        if kind in ("int", "float", "bool"):
            return getattr(loader, f"construct_yaml_{kind}")(ScalarNode(tag, value))
        raise _UnusualYamlError(tag)  # merge keys, timestamps, `=`

    no_key = _NO_KEY
    try:
        get = loader.get_event
        if type(get()) is not StreamStartEvent:
            raise _UnusualYamlError("stream")
        if type(get()) is StreamEndEvent:
            return None, 0, 0
        root: object = None
        stack: list[tuple[Any, bool, object]] = []
        container: Any = None  # the list or dict being filled (None: at the top)
        is_list = False
        key: object = no_key
        values = depth = 0
        while True:
            event = get()
            cls = type(event)
            if cls is ScalarEvent:
                if event.anchor is not None or event.tag is not None:
                    raise _UnusualYamlError("anchor or tag")
                value: Any = event.value
                if event.implicit[0]:  # a plain scalar: resolved once per distinct text (ids miss: no try)
                    text_value = value
                    value = scalars.get(text_value, no_key)
                    if value is no_key:
                        value = scalars[text_value] = plain(text_value)
                if is_list:
                    container.append(value)
                    values += 1
                elif container is None:
                    root = value
                elif key is no_key:
                    key = value
                else:
                    container[key] = value
                    key = no_key
                    values += 1
            elif cls is MappingStartEvent or cls is SequenceStartEvent:
                if event.anchor is not None or event.tag is not None:
                    raise _UnusualYamlError("anchor or tag")
                new: Any = {} if cls is MappingStartEvent else []
                if is_list:
                    container.append(new)
                    values += 1
                elif container is None:
                    root = new
                elif key is no_key:
                    raise _UnusualYamlError("complex key")
                else:
                    container[key] = new
                    key = no_key
                    values += 1
                depth = max(depth, len(stack))
                stack.append((container, is_list, key))
                container, is_list, key = new, cls is SequenceStartEvent, no_key
            elif cls is MappingEndEvent or cls is SequenceEndEvent:
                container, is_list, key = stack.pop()
            elif cls is DocumentEndEvent:
                break
            else:
                raise _UnusualYamlError(cls.__name__)  # aliases
        if type(get()) is not StreamEndEvent:
            raise _UnusualYamlError("several documents")
        return root, values, depth
    finally:
        loader.dispose()


_NO_KEY = object()
