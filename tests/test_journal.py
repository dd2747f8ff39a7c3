"""The mission journal: round trips, refusals, clean errors, and a real `kill -9` mid-write."""

from __future__ import annotations

import json
import math
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from palletpilot.executor.adapters.stores.journal import SCHEMA_VERSION, Journal, JournalError

META = {"mission": "/missions/pickup.yaml", "mission_sha256": "ab" * 32, "seed": 7, "report_dir": None}


def test_create_checkpoint_reopen_round_trip(tmp_path: Path):
    path = tmp_path / "deep" / "folder" / "run.journal"  # parent folders are created
    with Journal.create(path, META) as j:
        assert j.meta == META and not j.finished and j.sequence == 0
        assert j.last_checkpoint() is None and j.checkpoints() == []
        assert j.checkpoint({"task": 0, "state": "drive", "x": 1.5}) == 1
        # Strict JSON: non-finite numbers become null, tuples lists, big ints stay exact.
        assert j.checkpoint({"task": 0, "state": "lift", "x": math.nan, "p": (1, 2), "rng": 2**127 + 3}) == 2
    with pytest.raises(JournalError, match="closed"):
        j.checkpoint({})

    j = Journal.open(path)
    assert j.meta == META
    assert j.sequence == 2
    assert j.last_checkpoint() == {"task": 0, "state": "lift", "x": None, "p": [1, 2], "rng": 2**127 + 3}
    assert [c["state"] for c in j.checkpoints()] == ["drive", "lift"]
    assert (j.mark_resumed(), j.mark_resumed()) == (1, 2)
    assert j.checkpoint({"task": 1, "state": None}) == 3
    assert j.outcome is None
    j.finish(False, "pallet_not_found")
    assert j.finished and j.outcome == {"success": False, "reason": "pallet_not_found"}
    with pytest.raises(JournalError, match="finished; no more checkpoints"):
        j.checkpoint({"task": 2})
    j.close()
    j.close()  # idempotent

    j = Journal.open(path)
    assert j.finished and j.resumes == 2 and j.sequence == 3
    assert j.outcome == {"success": False, "reason": "pallet_not_found"}
    j.close()
    with sqlite3.connect(path) as db:  # the file is what the docstring says
        assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        assert db.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION


def test_create_refuses_an_unfinished_run_and_replaces_a_finished_one(tmp_path: Path):
    path = tmp_path / "run.journal"
    j = Journal.create(path, META)
    j.checkpoint({"task": 0})
    j.close()
    with pytest.raises(JournalError) as info:
        Journal.create(path, {"other": True})
    assert str(info.value) == f"{path}: holds an unfinished run; resume it with --resume or remove the file"
    assert Journal.open(path).sequence == 1  # untouched

    j = Journal.open(path)
    j.finish(True)
    j.close()
    with Journal.create(path, {"run": 2}) as new:
        assert new.meta == {"run": 2} and new.sequence == 0 and not new.finished
        assert new.checkpoint({"task": 0}) == 1


def test_an_empty_leftover_is_replaced_but_other_files_are_not(tmp_path: Path):
    empty = tmp_path / "empty.journal"
    empty.write_bytes(b"")  # a create killed before its first commit
    Journal.create(empty, META).close()
    assert Journal.open(empty).meta == META

    notes = tmp_path / "notes.txt"
    notes.write_text("precious")
    with pytest.raises(JournalError, match="not a palletpilot journal"):
        Journal.create(notes, META)
    assert notes.read_text() == "precious"


def test_missing_garbage_and_foreign_files_give_one_line_errors(tmp_path: Path):
    cases = {}
    cases["missing"] = tmp_path / "nope.journal"
    cases["garbage"] = tmp_path / "garbage.journal"
    cases["garbage"].write_bytes(os.urandom(4096))
    cases["empty"] = tmp_path / "empty.journal"
    cases["empty"].write_bytes(b"")
    cases["truncated"] = tmp_path / "truncated.journal"
    cases["truncated"].write_bytes(b"SQLite format 3\x00" + os.urandom(200))
    cases["foreign"] = tmp_path / "foreign.db"
    with sqlite3.connect(cases["foreign"]) as db:
        db.execute("CREATE TABLE t (x)")
    db.close()
    cases["folder"] = tmp_path / "a_folder"
    cases["folder"].mkdir()
    messages = {}
    for name, path in cases.items():
        with pytest.raises(JournalError) as info:
            Journal.open(path)
        messages[name] = str(info.value)
        assert str(path) in messages[name] and "\n" not in messages[name], messages[name]
    assert "no such journal file" in messages["missing"]
    assert "not an SQLite database" in messages["garbage"]
    assert "empty file" in messages["empty"]
    assert "not a" in messages["truncated"]
    assert "SQLite database of something else" in messages["foreign"]


def test_a_newer_format_or_a_journal_without_meta_is_refused(tmp_path: Path):
    path = tmp_path / "run.journal"
    Journal.create(path, META).close()
    with sqlite3.connect(path) as db:
        db.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    db.close()
    with pytest.raises(JournalError, match=rf"format version {SCHEMA_VERSION + 1}, this palletpilot reads version 1"):
        Journal.open(path)
    with sqlite3.connect(path) as db:
        db.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
        db.execute("DELETE FROM run")
    db.close()
    with pytest.raises(JournalError, match="no run description"):
        Journal.open(path)


def test_a_failed_write_is_one_line_and_leaves_the_journal_intact(tmp_path: Path):
    path = tmp_path / "run.journal"
    j = Journal.create(path, META)
    assert j.checkpoint({"task": 0, "state": "drive"}) == 1
    # A full disk, as SQLite sees one: the database may not grow by another page.
    pages = j._db().execute("PRAGMA page_count").fetchone()[0]
    j._db().execute(f"PRAGMA max_page_count = {pages}")
    with pytest.raises(JournalError) as info:
        j.checkpoint({"task": 0, "state": "lift", "blob": "x" * 200_000})
    assert str(info.value).startswith(f"{path}: cannot write a checkpoint: ") and "full" in str(info.value)
    assert "\n" not in str(info.value)
    assert j.sequence == 1 and j.last_checkpoint() == {"task": 0, "state": "drive"}
    j.close()
    assert Journal.open(path).last_checkpoint() == {"task": 0, "state": "drive"}


_CHILD = r"""
import sys
from palletpilot.executor.adapters.stores.journal import Journal

journal = Journal.create(sys.argv[1], {"child": True})
n = 0
while True:
    n += 1
    seq = journal.checkpoint({"n": n, "payload": [n * k for k in range(200)], "text": "x" * (n % 50) * 100})
    print(seq, flush=True)
"""


def _intact(doc: dict) -> bool:
    n = doc["n"]
    return doc["payload"] == [n * k for k in range(200)] and doc["text"] == "x" * (n % 50) * 100


def test_kill_9_while_writing_leaves_the_last_committed_checkpoint(tmp_path: Path):
    path = tmp_path / "crash.journal"
    child = subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert child.stdout is not None
        reported = []
        deadline = time.monotonic() + 60.0
        while len(reported) < 30 and time.monotonic() < deadline:
            line = child.stdout.readline()
            if not line:
                break
            reported.append(int(line))
        assert len(reported) >= 30, child.stderr.read() if child.stderr else ""
        os.kill(child.pid, signal.SIGKILL)  # mid-loop: most likely between or inside a commit
        child.wait(timeout=30)
        reported += [int(line) for line in child.stdout.read().split()]  # lines already in the pipe
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    assert child.returncode == -signal.SIGKILL
    assert reported == list(range(1, len(reported) + 1))

    j = Journal.open(path)
    last = j.last_checkpoint()
    assert last is not None and _intact(last)
    assert j.sequence in (reported[-1], reported[-1] + 1)  # committed, perhaps not yet printed
    assert last["n"] == j.sequence
    assert all(_intact(c) for c in j.checkpoints())
    assert not j.finished and j.meta == {"child": True}
    j.close()
    with pytest.raises(JournalError, match="holds an unfinished run"):
        Journal.create(path, META)
    json.dumps(last)  # plain JSON
