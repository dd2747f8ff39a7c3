"""`palletpilot test --executor ray` on a real two-node Ray cluster on loopback (`ray start --head` plus a
second node, both on 127.0.0.1, one CPU each): a suite whose folder is deleted once the head has read
its inputs runs across both nodes from the object store with the local verdicts; then the second node
is killed while it runs a task: the runs finish on the head node with the local executor's verdicts,
the lost one marked `retried`. The cluster is started once for both tests (in this order).

Each node is a `ray start --block` in its own process group, stopped by that group's id and the ids of
the processes under it. Skipped where
Ray is not installed (`pip install 'palletpilot[cluster]'`); about a minute on two cores."""

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from palletpilot.geometry.fileio import bundled_path

pytest.importorskip("ray")

SUITE = bundled_path("missions") / "suite" / "suite.yaml"
RUNS = "person_on_the_route,box_in_the_entry,wrong_pallet_type,no_pallet_at_the_node"
BIN = Path(sys.executable).parent
ENV = {**os.environ, "RAY_AUTH_MODE": "disabled"}  # a throw-away cluster on this machine: no token to hand round


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _node(args: list[str], log: Path) -> subprocess.Popen:
    common = ["--block", "--node-ip-address=127.0.0.1", "--num-cpus=1", "--object-store-memory=200000000"]
    with log.open("wb") as out:
        return subprocess.Popen(
            [str(BIN / "ray"), "start", *common, *args],
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            env=ENV,
        )


def _descendants(root: int) -> dict[int, bytes]:
    """The processes under `root` (children, their children, ...): pid -> command line."""
    parent, cmd = {}, {}
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
            parent[int(pid)] = int(stat.rsplit(")", 1)[1].split()[1])
            cmd[int(pid)] = Path(f"/proc/{pid}/cmdline").read_bytes()
        except (OSError, ValueError, IndexError):
            continue
    out: dict[int, bytes] = {}
    todo = [root]
    while todo:
        here = todo.pop()
        for pid, ppid in parent.items():
            if ppid == here and pid not in out:
                out[pid] = cmd[pid]
                todo.append(pid)
    return out


def _stop(node: subprocess.Popen) -> None:
    """Stop a node: the `ray start` we started, its process group and every process under it, by id."""
    under = _descendants(node.pid)
    if node.poll() is None:
        os.killpg(node.pid, signal.SIGTERM)
        try:
            node.wait(timeout=20)
        except subprocess.TimeoutExpired:
            pass
    for pid in [node.pid, *under]:
        try:
            os.kill(pid, signal.SIGKILL)  # anything left behind (Ray's workers may leave the group)
        except ProcessLookupError:
            pass
    node.wait(timeout=10)


def _alive_nodes(address: str) -> int:
    code = f"import ray; ray.init(address='{address}'); print(len([n for n in ray.nodes() if n['Alive']]))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=ENV)
    return int(out.stdout.strip().splitlines()[-1]) if out.returncode == 0 and out.stdout.strip() else 0


@pytest.fixture(scope="module")
def cluster() -> Iterator[tuple[str, subprocess.Popen]]:
    temp = Path(tempfile.mkdtemp(prefix="pp-ray-", dir="/tmp"))  # short: Ray's socket paths have a length limit
    port = _free_port()
    address = f"127.0.0.1:{port}"
    head = _node(["--head", f"--port={port}", "--include-dashboard=false", f"--temp-dir={temp}"], temp / "head.log")
    nodes = [head]
    try:
        deadline = time.monotonic() + 90
        while _alive_nodes(address) < 1:
            assert time.monotonic() < deadline and head.poll() is None, (temp / "head.log").read_text()[-2000:]
        second = _node([f"--address={address}"], temp / "second.log")
        nodes.append(second)
        while _alive_nodes(address) < 2:
            assert time.monotonic() < deadline and second.poll() is None, (temp / "second.log").read_text()[-2000:]
        yield address, second
    finally:
        for node in reversed(nodes):
            _stop(node)
        shutil.rmtree(temp, ignore_errors=True)


def test_the_inputs_travel_with_the_tasks_to_both_nodes(cluster, tmp_path, monkeypatch):
    from test_suite_inputs import VERDICT, make_site

    address, _ = cluster
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    monkeypatch.chdir(tmp_path)
    suite_file = make_site(tmp_path / "site").relative_to(tmp_path)
    local = tmp_path / "local"
    assert (
        subprocess.run([str(BIN / "palletpilot"), "test", str(suite_file), "--report", str(local)], env=ENV).returncode
        == 1
    )
    # The head in a fresh process, as `palletpilot test` runs it: a Ray driver in this one would inherit the
    # node address cached by an earlier in-process local Ray instance (tests/test_suite_ray.py), and the
    # second node could then not reach the inputs' owner.
    head = (
        "import json, shutil, sys\n"
        "from pathlib import Path\n"
        "from palletpilot.executor.apps.suite import load_suite\n"
        "from palletpilot.executor.apps.suite_inputs import gather_inputs\n"
        "from palletpilot.executor.apps.suite_ray import run_on_ray\n"
        "suite_file, address = Path(sys.argv[1]), sys.argv[2]\n"
        "specs = load_suite(suite_file).runs()\n"
        "inputs = gather_inputs(specs, suite_file)\n"
        "shutil.rmtree('site')  # no node can read the suite's folder now\n"
        "out = run_on_ray(specs, Path('ray'), address, None, lambda r, done: None, inputs)\n"
        "print(json.dumps({'jobs': out.jobs, 'interrupted': out.interrupted,\n"
        "                  'results': [r.to_json() for r in out.results]}))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", head, str(suite_file), address], env=ENV, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert not (tmp_path / "site").exists()
    outcome = json.loads(done.stdout.strip().splitlines()[-1])
    assert outcome["jobs"] == 2 and not outcome["interrupted"]
    on_ray = outcome["results"]
    want = json.loads((local / "suite.json").read_text())["results"]
    assert [{k: r[k] for k in VERDICT} for r in on_ray] == [{k: r[k] for k in VERDICT} for r in want]
    assert len({r["started_s"] for r in on_ray}) == len(on_ray) and not any(r["retried"] for r in on_ray)
    assert (tmp_path / "ray" / "aisle" / "1" / "run.mcap").is_file()


def test_a_suite_across_two_nodes_survives_losing_one(cluster, tmp_path):
    address, second = cluster
    local = tmp_path / "local"
    run = [str(BIN / "palletpilot"), "test", str(SUITE), "--only", RUNS, "--json"]
    assert subprocess.run([*run, "--report", str(local)], capture_output=True, timeout=600, env=ENV).returncode == 0
    proc = subprocess.Popen(
        [*run, "--executor", "ray", "--ray-address", address, "--report", str(tmp_path / "ray")],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=ENV,
    )
    deadline = time.monotonic() + 120
    busy = b"ray::run_remote"  # Ray names a worker by the task it runs
    while not any(busy in cmd for cmd in _descendants(second.pid).values()):  # a run on the second node
        assert time.monotonic() < deadline and proc.poll() is None, "no run reached the second node"
        time.sleep(0.05)
    _stop(second)  # the node is lost with the run on it
    out, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err.decode()[-3000:]
    on_ray = json.loads(out)["results"]
    want = json.loads((local / "suite.json").read_text())["results"]
    keys = ("label", "outcome", "met", "reason", "problems", "simulated_s")
    assert [{k: r[k] for k in keys} for r in on_ray] == [{k: r[k] for k in keys} for r in want]
    assert sum(r["retried"] for r in on_ray) == 1  # the run that was on the lost node, run again on the head
