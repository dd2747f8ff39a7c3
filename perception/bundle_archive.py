"""Reading a frame bundle file (`.npz`) safely: the archive's directory and array headers before any data.

Public API:
- Limits: `MAX_BUNDLE_FILE_BYTES`, `MAX_BUNDLE_BYTES`, `MAX_MEMBERS`, `MAX_HEADER_BYTES`.
- Package-internal (`perception.frames.load_bundle`): `_read_arrays(path)`, every array of a bundle
  file once its directory and headers passed the checks, or `PerceptionError`.

`perception.frames` re-exports the limits; import them from there. No frames: this module reads
arrays, `perception.frames` builds the `FrameBundle` (whose constructor checks the contract,
`perception.bundle_contract`).

A bundle file may come from anywhere (a camera, a colleague, a damaged disk, someone hostile), so
`load_bundle` reads the `.npz` (a zip of `.npy` arrays) with `zipfile` itself: the archive's
directory and every array's `.npy` header come first, and keys, dtypes, shapes and sizes are checked
against the limits (`MAX_BUNDLE_FILE_BYTES`, `MAX_MEMBERS`, `MAX_BUNDLE_BYTES`) before a single
array is decompressed: a 1.5 MB file never unpacks into gigabytes, a header declaring a 100000 x
100000 image is refused from its 100 bytes, and object arrays (pickles) are never loaded. A damaged
archive (bit flips, truncation, CRC errors, a header that does not match its data) is
`FILE: corrupt frame bundle: ...`. Every problem is one line that starts with the file's path
(`FILE: KEY: problem`), and every problem of a file is reported (`PerceptionError.problems`).
"""

from __future__ import annotations

import io
import math
import re
import stat
import struct
import zipfile
import zlib
from collections.abc import Mapping
from pathlib import Path
from typing import IO, NamedTuple

import numpy as np

from palletpilot.perception.bundle_contract import (
    BUNDLE_KEYS,
    DIST_LENGTHS,
    MAX_IMAGE_SIDE,
    MAX_TRUTH_ELEMENTS,
    TRUTH_SUFFIX,
    _error,
    _image_shape_ok,
)
from palletpilot.perception.errors import PerceptionError

MAX_BUNDLE_FILE_BYTES = 256 * 2**20
"""The largest bundle file read (bytes): a 4096 x 4096 bundle of noise compresses to about 130 MiB."""
MAX_BUNDLE_BYTES = 256 * 2**20
"""The most bytes all arrays of one bundle may unpack into (4096 x 4096 depth, labels and rgb: 128 MiB)."""
MAX_MEMBERS = 64
"""The most arrays (zip members) a bundle file may hold."""
MAX_HEADER_BYTES = 10_000
"""The longest `.npy` header read (numpy's own limit for parsing one safely)."""

_KEY_PATTERN = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,63}")
_CHUNK_BYTES = 4 * 2**20

_CORRUPT = (
    zipfile.BadZipFile,
    zlib.error,
    EOFError,
    OSError,
    ValueError,
    NotImplementedError,
    RuntimeError,
    struct.error,
    OverflowError,
    KeyError,
)
"""What a damaged archive raises while it is read (zipfile, zlib, numpy's header parser)."""


class _Header(NamedTuple):
    """An `.npy` member's header: array shape, Fortran order, dtype and header length (bytes)."""

    shape: tuple[int, ...]
    fortran: bool
    dtype: np.dtype
    offset: int

    @property
    def nbytes(self) -> int:
        """Bytes of array data the header declares (Python ints: no overflow)."""
        return math.prod(self.shape) * self.dtype.itemsize


def _describe(exc: BaseException) -> str:
    """One line saying what a corrupt archive raised."""
    if isinstance(exc, zlib.error):
        return f"compressed data damaged ({exc})"
    if isinstance(exc, EOFError):
        return f"truncated: the data ends early ({exc})" if str(exc) else "truncated: the data ends early"
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text[:300]


def _zip_entry_count(f: IO[bytes], size: int) -> int | None:
    """The member count in the zip's end-of-central-directory record, or None when there is none."""
    tail_len = min(size, 22 + 0xFFFF)
    f.seek(size - tail_len)
    tail = f.read(tail_len)
    i = tail.rfind(b"PK\x05\x06")
    if i < 0 or len(tail) - i < 22:
        return None
    return int(struct.unpack("<10xH10x", tail[i : i + 22])[0])


def _read_header(zf: zipfile.ZipFile, info: zipfile.ZipInfo) -> _Header:
    """Read one member's `.npy` header (only its first bytes are decompressed)."""
    with zf.open(info) as m:
        version = np.lib.format.read_magic(m)
        if version == (1, 0):
            fmt, reader = "<H", np.lib.format.read_array_header_1_0
        elif version == (2, 0):
            fmt, reader = "<I", np.lib.format.read_array_header_2_0
        else:
            raise ValueError(f".npy format version {version[0]}.{version[1]} is not read (1.0 and 2.0 are)")
        raw = m.read(struct.calcsize(fmt))
        if len(raw) < struct.calcsize(fmt):
            raise EOFError("in the array header")
        length = int(struct.unpack(fmt, raw)[0])
        if length > MAX_HEADER_BYTES:
            raise ValueError(f"an array header of {length} bytes (at most {MAX_HEADER_BYTES})")
        text = m.read(length)
        if len(text) < length:
            raise EOFError("in the array header")
        shape, fortran, dtype = reader(io.BytesIO(raw + text), max_header_size=MAX_HEADER_BYTES)
    return _Header(tuple(shape), bool(fortran), dtype, 6 + 2 + len(raw) + length)


def _read_data(zf: zipfile.ZipFile, info: zipfile.ZipInfo, header: _Header) -> np.ndarray:
    """Decompress one member's array, already checked against the limits, into a fresh array."""
    count = math.prod(header.shape)
    flat = np.empty(count, dtype=header.dtype)
    buf = flat.view(np.uint8).data  # a writable memoryview of the array's bytes
    with zf.open(info) as m:
        if len(m.read(header.offset)) < header.offset:
            raise EOFError("in the array header")
        pos = 0
        while pos < len(buf):
            chunk = m.read(min(_CHUNK_BYTES, len(buf) - pos))
            if not chunk:
                raise EOFError(f"after {pos} of {len(buf)} bytes of array data")
            buf[pos : pos + len(chunk)] = chunk
            pos += len(chunk)
        if m.read(1):  # also completes the CRC check
            raise ValueError("more data than the array header declares")
    if header.fortran:
        return flat.reshape(header.shape[::-1]).T
    return flat.reshape(header.shape)


def _header_problems(headers: Mapping[str, _Header], sizes: Mapping[str, int], where: str) -> list[str]:
    """One line per key whose header breaks the contract or the limits (nothing decompressed yet).

    `sizes`: each member's uncompressed size from the zip directory, which must be the header's
    length plus the data its shape and dtype declare (else the archive is corrupt).
    """
    problems: list[str] = []
    flagged: set[str] = set()

    def bad(key: str, problem: str) -> None:
        problems.append(f"{where}: {key}: {problem}")
        flagged.add(key)

    channels = {"depth": (), "labels": (), "rgb": (3,)}
    for key, h in headers.items():
        if h.dtype.hasobject:
            bad(key, "an object array (a pickle): refused, a bundle holds plain numbers")
        elif any(n < 0 for n in h.shape):
            problems.append(f"{where}: corrupt frame bundle: {key}: negative size in shape {h.shape}")
            flagged.add(key)
        elif key in channels:
            dtype = np.float32 if key == "depth" else np.uint8
            shape = "H, W, 3" if key == "rgb" else "H, W"
            if h.dtype != dtype:
                bad(key, f"dtype must be {np.dtype(dtype)}{' (metres)' if key == 'depth' else ''}, got {h.dtype}")
            elif h.shape[2:] != channels[key] or not _image_shape_ok(h.shape[:2]):
                bad(key, f"shape must be ({shape}) with 1..{MAX_IMAGE_SIDE} px a side, got {h.shape}")
        elif key == "K":
            if h.dtype != np.float64:
                bad(key, f"dtype must be float64, got {h.dtype}")
            elif h.shape != (3, 3):
                bad(key, f"shape must be (3, 3), got {h.shape}")
        elif key == "fork_height":
            if h.shape != () or h.dtype.kind not in "fiu":
                bad(key, f"must be a scalar number, got shape {h.shape} dtype {h.dtype}")
        elif key == "dist":
            if h.dtype != np.float64 or len(h.shape) != 1 or h.shape[0] not in DIST_LENGTHS:
                bad(
                    key,
                    f"must be a float64 vector of {', '.join(map(str, DIST_LENGTHS[:-1]))} or {DIST_LENGTHS[-1]} "
                    f"OpenCV distortion coefficients, got shape {h.shape} dtype {h.dtype}",
                )
        elif key.endswith(TRUTH_SUFFIX):
            if h.dtype.kind not in "fiub":
                bad(key, f"truth arrays must be numeric, got dtype {h.dtype}")
            elif math.prod(h.shape) > MAX_TRUTH_ELEMENTS:
                bad(key, f"shape {h.shape}: more elements than a truth array may hold ({MAX_TRUTH_ELEMENTS})")
            elif key.startswith("T_") and h.shape != (4, 4):
                bad(key, f"a transform must be a finite 4 x 4 matrix, got shape {h.shape}")
    for key, h in headers.items():  # a header that does not match its member's size is not to be trusted
        if key not in flagged and sizes[key] != h.offset + h.nbytes:
            problems.append(
                f"{where}: corrupt frame bundle: {key}: the array header declares shape {h.shape} of "
                f"{h.dtype} ({h.nbytes} bytes) but the member holds {sizes[key] - h.offset} bytes of data"
            )
            flagged.add(key)
    if "depth" in headers and "depth" not in flagged:
        image = headers["depth"].shape
        for key in ("labels", "rgb"):
            im = headers.get(key)
            if im is not None and key not in flagged and im.shape != (*image, *channels[key]):
                bad(key, f"shape {im.shape} does not match depth {image} (must be {(*image, *channels[key])})")
    total = sum(h.nbytes for h in headers.values())
    if not problems and total > MAX_BUNDLE_BYTES:
        problems.append(
            f"{where}: too large: the arrays unpack to {total / 2**20:.0f} MiB "
            f"(limit {MAX_BUNDLE_BYTES / 2**20:.0f} MiB)"
        )
    return problems


def _read_arrays(path: Path) -> dict[str, np.ndarray]:
    """Every array of a bundle file, after its directory and headers passed the checks (module docstring)."""
    where = str(path)
    try:
        st = path.stat()
    except FileNotFoundError:
        raise PerceptionError(f"{where}: no such file") from None
    except OSError as exc:
        raise PerceptionError(f"{where}: cannot read: {exc.strerror or exc}") from None
    if stat.S_ISDIR(st.st_mode):
        raise PerceptionError(f"{where}: a folder, not a frame bundle (.npz)")
    if not stat.S_ISREG(st.st_mode):
        raise PerceptionError(f"{where}: not a regular file (a device or a pipe), not a frame bundle (.npz)")
    if st.st_size == 0:
        raise PerceptionError(f"{where}: empty file, not a frame bundle (.npz)")
    if st.st_size > MAX_BUNDLE_FILE_BYTES:
        raise PerceptionError(
            f"{where}: too large: {st.st_size / 2**20:.0f} MiB (a frame bundle is at most "
            f"{MAX_BUNDLE_FILE_BYTES / 2**20:.0f} MiB)"
        )
    try:
        f = path.open("rb")
    except OSError as exc:
        raise PerceptionError(f"{where}: cannot read: {exc.strerror or exc}") from None
    with f:
        try:
            head = f.read(6)
            if head == b"\x93NUMPY":
                raise PerceptionError(f"{where}: not an .npz archive (a single .npy array); a frame bundle is an .npz")
            if not head.startswith(b"PK"):
                raise PerceptionError(f"{where}: not a frame bundle: not an .npz (zip) archive")
            entries = _zip_entry_count(f, st.st_size)
            if entries is None:
                raise PerceptionError(
                    f"{where}: corrupt frame bundle: no zip directory at the end (truncated or damaged)"
                )
            if entries > MAX_MEMBERS:
                raise PerceptionError(
                    f"{where}: too many arrays: {entries} (a frame bundle holds at most {MAX_MEMBERS})"
                )
            f.seek(0)
            with zipfile.ZipFile(f) as zf:
                return _read_members(zf, where)
        except _CORRUPT as exc:
            raise PerceptionError(f"{where}: corrupt frame bundle: {_describe(exc)}") from None


def _read_members(zf: zipfile.ZipFile, where: str) -> dict[str, np.ndarray]:
    """Check the archive's members and headers, then read the arrays (see `_read_arrays`)."""
    problems: list[str] = []
    members: dict[str, zipfile.ZipInfo] = {}
    infos = zf.infolist()
    if len(infos) > MAX_MEMBERS:
        raise PerceptionError(f"{where}: too many arrays: {len(infos)} (a frame bundle holds at most {MAX_MEMBERS})")
    declared = 0
    for info in infos:
        name = info.filename
        key = name[:-4] if name.endswith(".npy") else ""
        if not _KEY_PATTERN.fullmatch(key):
            problems.append(f"{where}: {name[:80]!r}: not an array of a frame bundle (KEY.npy)")
            continue
        if key in members:
            problems.append(f"{where}: corrupt frame bundle: {key}: stored twice")
            continue
        if key not in BUNDLE_KEYS and not key.endswith(TRUTH_SUFFIX):
            problems.append(
                f"{where}: {key}: unknown key (expected {', '.join(BUNDLE_KEYS)} or truth keys ending in "
                f"'{TRUTH_SUFFIX}')"
            )
            continue
        if info.flag_bits & 0x1:
            problems.append(f"{where}: {key}: encrypted; a frame bundle is never encrypted")
            continue
        if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
            problems.append(
                f"{where}: {key}: compression method {info.compress_type} (numpy writes only stored or deflated)"
            )
            continue
        declared += info.file_size
        members[key] = info
    for key in ("depth", "K"):
        if key not in members and not any(p.startswith(f"{where}: {key}: ") for p in problems):
            problems.append(f"{where}: {key}: missing (a bundle needs depth and K)")
    if declared > MAX_BUNDLE_BYTES + MAX_MEMBERS * MAX_HEADER_BYTES:  # sizes from the directory: nothing read
        problems.append(
            f"{where}: too large: the arrays unpack to {declared / 2**20:.0f} MiB "
            f"(limit {MAX_BUNDLE_BYTES / 2**20:.0f} MiB)"
        )
        raise _error(problems)

    headers: dict[str, _Header] = {}
    for key, info in members.items():
        try:
            headers[key] = _read_header(zf, info)
        except _CORRUPT as exc:
            raise PerceptionError(f"{where}: corrupt frame bundle: {key}: {_describe(exc)}") from None
    problems += _header_problems(headers, {k: i.file_size for k, i in members.items()}, where)
    if problems:
        raise _error(problems)

    arrays: dict[str, np.ndarray] = {}
    for key, info in members.items():
        try:
            arrays[key] = _read_data(zf, info, headers[key])
        except _CORRUPT as exc:
            raise PerceptionError(f"{where}: corrupt frame bundle: {key}: {_describe(exc)}") from None
    return arrays
