"""A crash-safe mission journal: one SQLite file per run, committed at every checkpoint.

The runner appends a JSON checkpoint whenever progress must survive a crash (ARCHITECTURE.md); each
`checkpoint()` is its own committed transaction in WAL mode with `synchronous=FULL`, so after a
`kill -9` or a power cut at any moment the file holds every checkpoint committed before it, the last
one intact. A resume (`palletpilot run --resume`) opens the journal, reads the last checkpoint and
continues from it.

Public API:

- `Journal.create(path, meta)`: a new journal (parent folders created). A file holding an unfinished
  run is refused (resume it or remove it); a finished run's journal, or an empty file, is replaced;
  any other file is refused.
- `Journal.open(path)`: an existing journal, for resume or inspection.
- `journal.meta`: the run's description given to `create` (JSON: mission, hashes, scenario, seed, ...).
- `journal.checkpoint(doc) -> int`: append and commit one checkpoint (strict JSON); its sequence number
  (1, 2, ...). `journal.sequence`: the last committed one (0 before any).
- `journal.last_checkpoint()`, `journal.checkpoints()`: the last one, all of them in order.
- `journal.mark_resumed() -> int`: count one more resume; `journal.resumes`: how many so far.
- `journal.finish(success, reason)`, `journal.finished`, `journal.outcome`: the run's end.
- `journal.close()`; a `Journal` is also a context manager.
- `JournalError`: every failure (missing file, not a journal, a newer format, a failed write), one line
  naming the file.

File format (`SCHEMA_VERSION` in `PRAGMA user_version`, `APPLICATION_ID` in `PRAGMA application_id`):
table `run` (one row: meta JSON, created / finished wall-clock times, success, reason, resumes) and
table `checkpoint` (seq, wall-clock time written, doc JSON). A file of another format is refused.
"""

from __future__ import annotations

import contextlib
import json
import os
import sqlite3
import time
from pathlib import Path
from types import TracebackType
from typing import Any

from palletpilot.geometry import PalletpilotError
from palletpilot.geometry.fileio import dumps_json

SCHEMA_VERSION = 1
"""The journal layout this module writes and reads (`PRAGMA user_version`)."""

APPLICATION_ID = 0x50504A4C  # "PPJL"
"""Marks an SQLite file as a palletpilot journal (`PRAGMA application_id`)."""

BUSY_TIMEOUT_S = 5.0
"""How long a write waits for another connection's lock before failing (s)."""

_SQLITE_MAGIC = b"SQLite format 3\x00"

_SCHEMA = (
    """CREATE TABLE run (
        id INTEGER PRIMARY KEY CHECK (id = 1),
        meta TEXT NOT NULL,
        created_unix_s REAL NOT NULL,
        finished INTEGER NOT NULL DEFAULT 0,
        success INTEGER,
        reason TEXT,
        finished_unix_s REAL,
        resumes INTEGER NOT NULL DEFAULT 0
    )""",
    """CREATE TABLE checkpoint (
        seq INTEGER PRIMARY KEY,
        written_unix_s REAL NOT NULL,
        doc TEXT NOT NULL
    )""",
)


class JournalError(PalletpilotError):
    """A journal that cannot be created, read or written; the message is one line naming the file."""


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


class Journal:
    """An open mission journal (see the module docstring). Build it with `create` or `open`."""

    def __init__(self, path: Path, conn: sqlite3.Connection, meta: dict[str, Any]) -> None:
        """Internal: use `Journal.create` or `Journal.open`."""
        self.path = path
        self.meta: dict[str, Any] = meta
        self._conn: sqlite3.Connection | None = conn

    # -- construction -------------------------------------------------------------------------------
    @classmethod
    def create(cls, path: str | Path, meta: dict[str, Any]) -> Journal:
        """A new journal at `path` for a run described by `meta` (JSON), committed before returning.

        Parent folders are created. An existing file holding an unfinished run raises `JournalError`
        (resume it with --resume or remove the file); a finished run's journal, or an empty file (a
        crash during an earlier create), is replaced; any other existing file is refused.
        """
        path = Path(path)
        meta_text = dumps_json(meta)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise JournalError(f"{path}: cannot create the journal's folder: {_one_line(exc)}") from None
        if path.exists():
            cls._clear_for_create(path)
        conn = cls._connect(path, create=True)
        try:
            conn.execute("PRAGMA journal_mode=WAL")
            conn.execute("PRAGMA synchronous=FULL")
            conn.execute("BEGIN IMMEDIATE")
            for statement in _SCHEMA:
                conn.execute(statement)
            conn.execute(
                "INSERT INTO run (id, meta, created_unix_s) VALUES (1, ?, ?)",
                (meta_text, time.time()),
            )
            conn.execute(f"PRAGMA application_id = {APPLICATION_ID}")
            conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
            conn.execute("COMMIT")
            _fsync_parent(path)
        except sqlite3.Error as exc:
            with contextlib.suppress(sqlite3.Error):
                conn.close()
            raise JournalError(f"{path}: cannot create the journal: {_one_line(exc)}") from None
        return cls(path, conn, json.loads(meta_text))

    @classmethod
    def open(cls, path: str | Path) -> Journal:
        """The existing journal at `path` (to resume or inspect a run).

        A missing file, a file that is not an SQLite database, another SQLite database, a newer
        journal format or a journal without its run description raise `JournalError` (one line).
        """
        path = Path(path)
        if not path.is_file():
            raise JournalError(f"{path}: no such journal file")
        cls._check_magic(path)
        conn = cls._connect(path, create=False)
        try:
            cls._check_schema(path, conn)
            row = conn.execute("SELECT meta FROM run WHERE id = 1").fetchone()
            if row is None:
                raise JournalError(f"{path}: the journal has no run description (meta); it is not usable")
            try:
                meta = json.loads(row[0])
            except (TypeError, ValueError):
                raise JournalError(f"{path}: the journal's run description (meta) is not JSON") from None
            if not isinstance(meta, dict):
                raise JournalError(f"{path}: the journal's run description (meta) is not a JSON object")
            conn.execute("PRAGMA synchronous=FULL")
        except JournalError:
            conn.close()
            raise
        except sqlite3.Error as exc:
            conn.close()
            raise JournalError(f"{path}: not a readable palletpilot journal: {_one_line(exc)}") from None
        return cls(path, conn, meta)

    @staticmethod
    def _connect(path: Path, create: bool) -> sqlite3.Connection:
        """An autocommit connection (each statement outside BEGIN ... COMMIT commits on its own)."""
        mode = "rwc" if create else "rw"
        try:
            return sqlite3.connect(
                f"{path.resolve().as_uri()}?mode={mode}", uri=True, isolation_level=None, timeout=BUSY_TIMEOUT_S
            )
        except sqlite3.Error as exc:
            raise JournalError(f"{path}: cannot open the journal: {_one_line(exc)}") from None

    @staticmethod
    def _check_magic(path: Path) -> None:
        try:
            with path.open("rb") as f:
                head = f.read(len(_SQLITE_MAGIC))
        except OSError as exc:
            raise JournalError(f"{path}: cannot read the journal: {_one_line(exc)}") from None
        if head != _SQLITE_MAGIC:
            what = "an empty file" if not head else "not an SQLite database"
            raise JournalError(f"{path}: not a palletpilot journal ({what})")

    @staticmethod
    def _check_schema(path: Path, conn: sqlite3.Connection) -> None:
        app_id = conn.execute("PRAGMA application_id").fetchone()[0]
        version = conn.execute("PRAGMA user_version").fetchone()[0]
        if app_id != APPLICATION_ID:
            raise JournalError(f"{path}: not a palletpilot journal (an SQLite database of something else)")
        if version != SCHEMA_VERSION:
            raise JournalError(
                f"{path}: journal format version {version}, this palletpilot reads version {SCHEMA_VERSION}"
            )

    @classmethod
    def _clear_for_create(cls, path: Path) -> None:
        """Remove an existing finished journal (or an empty leftover); refuse anything else."""
        if path.is_dir():
            raise JournalError(f"{path}: is a folder, not a journal file")
        if not cls._is_empty_database(path):
            try:
                old = cls.open(path)
            except JournalError as exc:  # not a journal: never overwritten
                raise JournalError(f"{exc}; it was left as it is (remove it or choose another file)") from None
            try:
                if not old.finished:
                    raise JournalError(f"{path}: holds an unfinished run; resume it with --resume or remove the file")
            finally:
                old.close()
        for suffix in ("", "-wal", "-shm"):
            try:
                Path(f"{path}{suffix}").unlink(missing_ok=True)
            except OSError as exc:
                raise JournalError(f"{path}: cannot replace the finished journal: {_one_line(exc)}") from None
        _fsync_parent(path)

    @classmethod
    def _is_empty_database(cls, path: Path) -> bool:
        """True for a zero-byte file or an SQLite file without tables (a create that crashed early)."""
        try:
            if path.stat().st_size == 0:
                return True
            with path.open("rb") as f:
                if f.read(len(_SQLITE_MAGIC)) != _SQLITE_MAGIC:
                    return False
        except OSError as exc:
            raise JournalError(f"{path}: cannot read the existing file: {_one_line(exc)}") from None
        try:
            conn = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True)
            try:
                return conn.execute("SELECT count(*) FROM sqlite_master").fetchone()[0] == 0
            finally:
                conn.close()
        except sqlite3.Error:
            return False

    # -- writing --------------------------------------------------------------------------------
    def _db(self) -> sqlite3.Connection:
        if self._conn is None:
            raise JournalError(f"{self.path}: the journal is closed")
        return self._conn

    def _write(self, sql: str, params: tuple[Any, ...], what: str) -> sqlite3.Cursor:
        """Run one statement as its own committed transaction; a failure raises `JournalError`."""
        conn = self._db()
        try:
            return conn.execute(sql, params)
        except sqlite3.Error as exc:
            if conn.in_transaction:
                with contextlib.suppress(sqlite3.Error):
                    conn.execute("ROLLBACK")
            raise JournalError(f"{self.path}: cannot {what}: {_one_line(exc)}") from None

    def checkpoint(self, doc: dict[str, Any]) -> int:
        """Append `doc` (strict JSON: NaN and infinities become null) and commit it; its sequence number.

        Sequence numbers start at 1 and grow by one. Raises `JournalError` once the run is finished or
        when the write fails (full disk, read-only file).
        """
        text = dumps_json(doc)
        if self.finished:
            raise JournalError(f"{self.path}: the run is finished; no more checkpoints")
        cur = self._write(
            "INSERT INTO checkpoint (written_unix_s, doc) VALUES (?, ?)", (time.time(), text), "write a checkpoint"
        )
        return int(cur.lastrowid or 0)

    def mark_resumed(self) -> int:
        """Count one more resume of the run (committed); how many there have been, this one included."""
        self._write("UPDATE run SET resumes = resumes + 1 WHERE id = 1", (), "record the resume")
        return self.resumes

    def finish(self, success: bool, reason: str | None = None) -> None:
        """Mark the run finished, with its outcome (committed). A later `create` may replace the file."""
        self._write(
            "UPDATE run SET finished = 1, success = ?, reason = ?, finished_unix_s = ? WHERE id = 1",
            (int(bool(success)), reason, time.time()),
            "record the end of the run",
        )

    # -- reading --------------------------------------------------------------------------------
    def _query(self, sql: str) -> list[tuple[Any, ...]]:
        try:
            return self._db().execute(sql).fetchall()
        except sqlite3.Error as exc:
            raise JournalError(f"{self.path}: cannot read the journal: {_one_line(exc)}") from None

    def _doc(self, text: str, seq: int) -> dict[str, Any]:
        try:
            doc = json.loads(text)
        except ValueError:
            raise JournalError(f"{self.path}: checkpoint {seq} is not JSON") from None
        if not isinstance(doc, dict):
            raise JournalError(f"{self.path}: checkpoint {seq} is not a JSON object")
        return doc

    @property
    def sequence(self) -> int:
        """The sequence number of the last committed checkpoint (0 before the first)."""
        return int(self._query("SELECT coalesce(max(seq), 0) FROM checkpoint")[0][0])

    def last_checkpoint(self) -> dict[str, Any] | None:
        """The last committed checkpoint, or None before the first."""
        rows = self._query("SELECT seq, doc FROM checkpoint ORDER BY seq DESC LIMIT 1")
        return self._doc(rows[0][1], rows[0][0]) if rows else None

    def checkpoints(self) -> list[dict[str, Any]]:
        """Every committed checkpoint, oldest first."""
        return [self._doc(text, seq) for seq, text in self._query("SELECT seq, doc FROM checkpoint ORDER BY seq")]

    @property
    def resumes(self) -> int:
        """How many times the run was resumed."""
        return int(self._query("SELECT resumes FROM run WHERE id = 1")[0][0])

    @property
    def finished(self) -> bool:
        """True once `finish` was committed."""
        return bool(self._query("SELECT finished FROM run WHERE id = 1")[0][0])

    @property
    def outcome(self) -> dict[str, Any] | None:
        """`{"success": bool, "reason": str | None}` of a finished run, None while it is unfinished."""
        finished, success, reason = self._query("SELECT finished, success, reason FROM run WHERE id = 1")[0]
        return {"success": bool(success), "reason": reason} if finished else None

    # -- life -----------------------------------------------------------------------------------
    def close(self) -> None:
        """Close the file (everything is committed already); idempotent."""
        if self._conn is not None:
            with contextlib.suppress(sqlite3.Error):
                self._conn.close()
            self._conn = None

    def __enter__(self) -> Journal:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Journal({str(self.path)!r})"


def _fsync_parent(path: Path) -> None:
    """Make a file's creation or removal durable (a no-op where folders cannot be opened)."""
    with contextlib.suppress(OSError):
        fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
