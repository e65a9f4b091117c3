# SPDX-License-Identifier: BSD-3-Clause
"""Tests of `uwbfuse batch` (uwbfuse.fleet) on real Dask processes, loopback only.

A real `dask scheduler` and two `dask worker` processes are started on 127.0.0.1 for the
module, run a batch of small simulated logs plus a corrupt file, and are killed at the
end. Each good log's trajectory must be byte-identical to the single-machine `run_log`.
"""

from __future__ import annotations

import csv
import importlib.util
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from uwbfuse import fleet
from uwbfuse.cli import main
from uwbfuse.config import Config
from uwbfuse.errors import FleetError
from uwbfuse.estimator import Method
from uwbfuse.fleet import batch_run, job_names, table_markdown

HAVE_DASK = importlib.util.find_spec("distributed") is not None
needs_dask = pytest.mark.skipif(
    not HAVE_DASK,
    reason="dask.distributed not installed (pip install 'uwbfuse[fleet]'); CI installs it",
)
# Bounded: every cluster wait below has its own deadline; this is the backstop.
pytestmark = pytest.mark.timeout(180)
METHOD = Method.ODOM
N_GOOD = 3
START_TIMEOUT_S = 30.0


def _simulated_log(path: Path, seed: int, duration_s: float = 12.0) -> Path:
    from uwbfuse.io.writer import write_contract_log
    from uwbfuse.sim.simulator import simulate

    write_contract_log(path, simulate("room", duration_s=duration_s, seed=seed))
    return path


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, list[Path]]:
    """Three small simulated logs, a corrupt file, and each good log's `run_log` TUM."""
    from uwbfuse.pipeline import run_log

    d = tmp_path_factory.mktemp("logs")
    good = [_simulated_log(d / f"agv{i}.mcap", seed=i) for i in range(N_GOOD)]
    corrupt = d / "corrupt.mcap"
    corrupt.write_bytes(b"\x89MCAP0\r\n" + os.urandom(3000))
    refs = []
    for lg in good:
        ref = d / f"{lg.stem}.ref.tum"
        run_log(lg, METHOD, Config(), tum_out=ref)
        refs.append(ref)
    return {"good": good, "corrupt": [corrupt], "ref": refs}


class DaskProcesses:
    """A `dask scheduler` and `dask worker` subprocesses, each in its own process group."""

    def __init__(self, workdir: Path, n_workers: int) -> None:
        self.workdir = workdir
        workdir.mkdir(parents=True, exist_ok=True)
        self.procs: list[subprocess.Popen[bytes]] = []
        self.workers: list[subprocess.Popen[bytes]] = []
        sched_file = workdir / "scheduler.json"
        self.scheduler = self._spawn(
            ["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
             "--dashboard-address", "127.0.0.1:0", "--idle-timeout", "120s",
             "--scheduler-file", str(sched_file)], "scheduler.log",
        )
        deadline = time.monotonic() + START_TIMEOUT_S
        while True:
            try:
                self.address = json.loads(sched_file.read_text())["address"]
                break
            except (OSError, ValueError, KeyError):
                if time.monotonic() > deadline or self.scheduler.poll() is not None:
                    self.close()
                    pytest.fail("dask scheduler did not start: " + self.log("scheduler.log"))
                time.sleep(0.05)
        for i in range(n_workers):
            self.workers.append(self._spawn(
                ["worker", self.address, "--nthreads", "1", "--nworkers", "1",
                 "--no-dashboard", "--host", "127.0.0.1", "--name", f"w{i}",
                 "--death-timeout", "20", "--local-directory", str(workdir / f"w{i}")],
                f"worker{i}.log",
            ))
        from distributed import Client

        with Client(self.address, timeout=START_TIMEOUT_S) as c:
            c.wait_for_workers(n_workers, timeout=START_TIMEOUT_S)

    def _spawn(self, args: list[str], logname: str) -> subprocess.Popen[bytes]:
        out = (self.workdir / logname).open("wb")
        proc = subprocess.Popen(
            [sys.executable, "-m", "dask", *args], stdout=out, stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL, start_new_session=True, cwd=self.workdir,
        )
        out.close()
        self.procs.append(proc)
        return proc

    def log(self, name: str) -> str:
        return (self.workdir / name).read_text(errors="replace")[-2000:]

    @staticmethod
    def kill(proc: subprocess.Popen[bytes]) -> None:
        """SIGKILL the process group (nanny and worker alike), as a machine dying would."""
        if proc.poll() is None:
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        proc.wait(timeout=10)

    def close(self) -> None:
        for proc in reversed(self.procs):
            self.kill(proc)


@pytest.fixture(scope="module")
def dask_cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[DaskProcesses]:
    if not HAVE_DASK:
        pytest.skip("dask.distributed not installed")
    procs = DaskProcesses(tmp_path_factory.mktemp("dask"), n_workers=2)
    try:
        yield procs
    finally:
        procs.close()


def _rows_by_log(result: fleet.BatchResult) -> dict[str, dict]:
    return {Path(r["log"]).name: r for r in result.rows}


def _check_good(result: fleet.BatchResult, logs: dict[str, list[Path]], out: Path) -> None:
    rows = _rows_by_log(result)
    for lg, ref in zip(logs["good"], logs["ref"], strict=True):
        row = rows[lg.name]
        assert row["status"] == "ok", row
        tum = out / f"{lg.stem}.{METHOD.value}.tum"
        assert tum.read_bytes() == ref.read_bytes(), f"{lg.name}: differs from run_log"
        lines = [ln for ln in tum.read_text().splitlines() if not ln.startswith("#")]
        assert row["poses"] == len(lines) >= 10
        assert row["ate_align"] == "se2" and 0 < row["ate2d_rmse_m"] <= row["ate3d_rmse_m"] < 1
        assert row["duration_s"] == pytest.approx(12.0, abs=0.5)


@needs_dask
def test_batch_on_scheduler_matches_run_and_reports_corrupt_log(
    dask_cluster: DaskProcesses, logs: dict[str, list[Path]], tmp_path: Path
) -> None:
    """Test that a batch on an external scheduler reproduces `run` and isolates a bad log."""
    out = tmp_path / "out"
    all_logs = [*logs["good"], *logs["corrupt"]]
    result = batch_run(all_logs, METHOD, out_dir=out, scheduler=dask_cluster.address)
    assert result.cluster.kind == "remote" and result.cluster.n_workers == 2
    _check_good(result, logs, out)
    bad = _rows_by_log(result)["corrupt.mcap"]
    assert bad["status"] == "failed"
    assert "corrupt.mcap" in bad["error"] and "\n" not in bad["error"]
    assert not (out / f"corrupt.{METHOD.value}.tum").exists()
    with (out / "summary.csv").open() as f:
        summary = list(csv.DictReader(f))
    assert [Path(r["log"]).name for r in summary] == [p.name for p in all_logs]
    assert [r["status"] for r in summary] == ["ok"] * N_GOOD + ["failed"]
    assert "| failed |" in (out / "summary.md").read_text()
    assert (out / "config.toml").read_text().startswith("# uwbfuse configuration")
    hosts = {r["host"] for r in result.rows if r["status"] == "ok"}
    assert all(h.split(":")[1] != str(os.getpid()) for h in hosts), "ran in the client"


@pytest.fixture(scope="module")
def long_logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, list[Path]]:
    """Three 90 s logs and their `run_log` TUMs for `imu` (~0.4 s a job): long enough
    that a worker killed after the first result is still busy with another job."""
    from uwbfuse.pipeline import run_log

    d = tmp_path_factory.mktemp("long")
    good = [_simulated_log(d / f"long{i}.mcap", seed=10 + i, duration_s=90.0)
            for i in range(3)]
    refs = []
    for lg in good:
        refs.append(d / f"{lg.stem}.ref.tum")
        run_log(lg, Method.IMU, Config(), tum_out=refs[-1])
    return {"good": good, "ref": refs}


@needs_dask
def test_batch_survives_a_worker_killed_mid_batch(
    long_logs: dict[str, list[Path]], tmp_path: Path
) -> None:
    """Test that killing one of two workers mid-batch still yields every result."""
    copies = []
    for k in range(2):
        for lg in long_logs["good"]:
            dst = tmp_path / "logs" / f"c{k}_{lg.name}"
            dst.parent.mkdir(exist_ok=True)
            shutil.copyfile(lg, dst)
            copies.append(dst)
    procs = DaskProcesses(tmp_path / "dask", n_workers=2)
    killed: list[float] = []
    seen: list[tuple[int, float]] = []

    def progress(done: int, total: int, note: str) -> None:
        seen.append((done, time.monotonic()))
        if done >= 1 and not killed:  # first job back: the others are queued or running
            procs.kill(procs.workers[0])
            killed.append(time.monotonic())

    try:
        out = tmp_path / "out"
        result = batch_run(copies, Method.IMU, out_dir=out, scheduler=procs.address,
                           progress=progress)
    finally:
        procs.close()
    assert len(killed) == 1 and seen[-1][0] == len(copies)
    # Five jobs of ~0.4 s were still to come when the worker died: mid-batch indeed.
    assert seen[-1][1] - killed[0] > 0.3
    assert result.n_ok == len(copies), [r["error"] for r in result.rows]
    ref = {lg.name: r.read_bytes() for lg, r in zip(*long_logs.values(), strict=True)}
    for cp in copies:
        original = cp.name.split("_", 1)[1]
        assert (out / f"{cp.stem}.imu.tum").read_bytes() == ref[original]
        assert (out / f"{cp.stem}.imu.json").exists()


@needs_dask
def test_batch_stops_when_no_worker_is_left(
    long_logs: dict[str, list[Path]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Test that losing the only worker ends the batch with a FleetError, not a hang,
    keeping the jobs done so far for resume."""
    monkeypatch.setattr(fleet, "WORKER_WAIT_S", 1.0)
    monkeypatch.setattr(fleet, "POLL_S", 0.2)
    procs = DaskProcesses(tmp_path / "dask", n_workers=1)

    def progress(done: int, total: int, note: str) -> None:
        if done == 1:
            procs.kill(procs.workers[0])

    out = tmp_path / "out"
    try:
        with pytest.raises(FleetError, match="no Dask workers left"):
            batch_run(long_logs["good"], Method.IMU, out_dir=out, scheduler=procs.address,
                      progress=progress)
    finally:
        procs.close()
    assert len(list(out.glob("*.imu.json"))) == 1


@needs_dask
def test_batch_local_cluster_and_resume(logs: dict[str, list[Path]], tmp_path: Path) -> None:
    """Test the in-process LocalCluster path, then that a re-run resumes complete jobs only."""
    out = tmp_path / "out"
    all_logs = [*logs["good"], *logs["corrupt"]]
    first = batch_run(all_logs, METHOD, out_dir=out, workers=2)
    assert first.cluster.kind == "local" and first.cluster.n_workers == 2
    _check_good(first, logs, out)
    assert first.n_failed == 1 and first.n_resumed == 0

    # Damage one trajectory: only that job (and the failed one) runs again.
    damaged = out / f"{logs['good'][1].stem}.{METHOD.value}.tum"
    damaged.write_bytes(damaged.read_bytes()[:100])
    calls: list[tuple[int, int]] = []
    second = batch_run(all_logs, METHOD, out_dir=out, workers=1,
                       progress=lambda d, t, n: calls.append((d, t)))
    resumed = [r["resumed"] for r in second.rows]
    assert resumed == [True, False, True, False]
    assert calls[0] == (2, 4) and calls[-1] == (4, 4)
    _check_good(second, logs, out)
    assert _rows_by_log(second)["corrupt.mcap"]["status"] == "failed"

    # A changed config invalidates every marker.
    cfg = tmp_path / "c.toml"
    cfg.write_text("[output]\nrate = 5.0\n")
    third = batch_run(logs["good"][:1], METHOD, config_path=cfg, out_dir=out, workers=1)
    assert third.n_resumed == 0 and third.rows[0]["poses"] < first.rows[0]["poses"]


def test_batch_inline_without_dask(
    logs: dict[str, list[Path]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Test that without dask the jobs run one by one here, with the same results."""
    monkeypatch.setattr(fleet, "_import_distributed", lambda: None)
    out = tmp_path / "out"
    result = batch_run([*logs["good"], *logs["corrupt"]], METHOD, out_dir=out)
    assert result.cluster.kind == "inline"
    _check_good(result, logs, out)
    assert result.rows[-1]["status"] == "failed"
    with pytest.raises(FleetError, match=r"needs dask\.distributed"):
        batch_run(logs["good"][:1], METHOD, out_dir=tmp_path / "o2", scheduler="tcp://x:1")


@needs_dask
def test_cli_batch_table_and_exit_status(
    dask_cluster: DaskProcesses, logs: dict[str, list[Path]], tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Test that `uwbfuse batch` prints the table and exits 2 when a log failed, else 0."""
    good = [str(p) for p in logs["good"]]
    opts = ["--method", METHOD.value, "--out-dir", str(tmp_path / "o"),
            "--scheduler", dask_cluster.address, "--dashboard"]
    assert main(["batch", *good, *opts]) == 0
    cap = capsys.readouterr()
    assert "| log | status |" in cap.out and f"{N_GOOD} of {N_GOOD} logs ok" in cap.out
    assert "dashboard:" in cap.err and "logs [" in cap.err
    assert main(["batch", *good, str(logs["corrupt"][0]), *opts]) == 2
    cap = capsys.readouterr()
    assert f"{N_GOOD} resumed" in cap.out
    assert "1 of 4 logs failed" in cap.err


@needs_dask
def test_unreachable_scheduler_is_one_clear_error(
    logs: dict[str, list[Path]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Test that a scheduler nobody listens on gives a FleetError naming the address."""
    import socket

    with socket.socket() as s:  # a free port, closed again: nothing listens there
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    monkeypatch.setattr(fleet, "CONNECT_TIMEOUT_S", 1.0)
    address = f"tcp://127.0.0.1:{port}"
    expected = re.escape(f"cannot reach the Dask scheduler at {address}")
    with pytest.raises(FleetError, match=expected):
        batch_run(logs["good"][:1], METHOD, out_dir=tmp_path / "o", scheduler=address)
    with pytest.raises(FleetError, match="bad Dask scheduler address 'nonsense'"):
        batch_run(logs["good"][:1], METHOD, out_dir=tmp_path / "o", scheduler="nonsense")


def test_job_names_are_unique_and_tables_escape() -> None:
    """Test that colliding log stems get a path digest and Markdown cells are escaped."""
    names = job_names(["/a/agv1.mcap", "/b/agv1.mcap", "/c/bag_dir/", "/d/x y.mcap"])
    assert names[0].startswith("agv1-") and names[1].startswith("agv1-")
    assert names[0] != names[1] and names[2:] == ["bag_dir", "x_y"]
    md = table_markdown(["a", "b"], [{"a": "x|y", "b": float("nan")}, {"a": "p\nq", "b": 1.5}])
    assert "x\\|y" in md and "| p q | 1.5 |" in md


def test_progress_bar_lines_on_a_pipe() -> None:
    """Test that off a terminal the bar writes whole lines, throttled, always the last."""
    import io

    from uwbfuse.progress import ProgressBar

    stream = io.StringIO()
    with ProgressBar("logs", stream=stream, width=10, min_interval_s=3600) as bar:
        for done in range(5):
            bar(done, 4, f"job{done}")
    lines = stream.getvalue().splitlines()
    assert lines[0].startswith("logs [..........] 0/4")
    assert lines[-1].startswith("logs [##########] 4/4") and lines[-1].endswith("job4")
    assert len(lines) == 2  # the middle updates fall inside the interval
