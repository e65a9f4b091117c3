# SPDX-License-Identifier: BSD-3-Clause
"""`uwbfuse batch` as a library function: one method over many logs on a Dask cluster.

`batch_run` reads as its steps: name the jobs, skip those already complete (resume), run
the rest on the cluster (one task per log; each worker reads its log from the path), write
each job's outputs as its result arrives, gather the summary table.

Layout of `out_dir`:

- `<job>.<method>.tum`: the trajectory, byte-identical to `uwbfuse run LOG -o ...`;
- `<job>.<method>.json`: the job's metrics row (written last: the done marker);
- `config.toml`: the effective configuration; `summary.csv`, `summary.md`: one row per log.

Every file is written whole or not at all (temporary file, then rename). Workers return
results to the client, which writes them, so `out_dir` need only exist where the client
runs; the logs must be reachable by the workers under the path given.

Isolation: a job catches everything its log or its method raises and returns a failed row
with the error text; a job whose worker dies is retried on another worker by Dask (up to
`distributed.scheduler.allowed-failures` times) and otherwise fails its own row. A cluster
left without any worker for `WORKER_WAIT_S`, or a lost scheduler, ends the batch with a
`FleetError`; the jobs finished so far are kept, and running again resumes.

The cluster: with no scheduler address, an in-process `LocalCluster` sized to the machine
(one single-threaded worker process per core); with an address, an existing cluster
(`dask scheduler` / `dask worker`). Without `dask.distributed` installed and no address,
jobs run one after another in this process. The generic machinery (`cluster`, `run_jobs`,
`write_atomic`, tables) is shared with `uwbfuse.montecarlo`.
"""

from __future__ import annotations

import csv
import hashlib
import importlib.metadata
import io
import json
import logging
import math
import os
import socket
import tempfile
import time
import traceback
import uuid
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any

from uwbfuse.config import Config, config_from_dict, dump_config, load_config
from uwbfuse.errors import FleetError, UwbfuseError
from uwbfuse.estimator import Method
from uwbfuse.io import atomic
from uwbfuse.progress import ProgressFn
from uwbfuse.streams import PoseStream

log = logging.getLogger(__name__)

DONE_FORMAT = 1
WORKER_WAIT_S = 30.0
"""Seconds to wait for a scheduler, or for a worker when the cluster has none."""
POLL_S = 2.0
CONNECT_TIMEOUT_S = 10.0
MAX_ERROR_CHARS = 400

SUMMARY_COLUMNS: tuple[str, ...] = (
    "log", "status", "error", "duration_s", "poses", "ate2d_rmse_m", "ate3d_rmse_m",
    "ate_align", "wall_s", "cpu_s", "read_s",
    "estimate_s", "realtime_factor", "skipped", "tum", "host", "resumed",
)
"""Columns of `summary.csv` / `summary.md`, in order."""


# --------------------------------------------------------------------------------------
# Files: atomic writes and tables


def write_atomic(path: str | Path, data: bytes | str) -> None:
    """Write `data` to `path` whole or not at all (fsync, rename), creating the folder.
    Raises FleetError naming the file on failure."""
    p = Path(path)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise FleetError(f"{p.parent}: cannot create folder: {e.strerror or e}") from None
    atomic.write_atomic(p, data, error=FleetError, what="file", fsync=True)


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        if math.isnan(value):
            return ""
        return f"{value:.6g}"
    return str(value)


def table_csv(columns: Sequence[str], rows: Sequence[dict[str, Any]]) -> str:
    """Rows as CSV text (header first; missing values empty)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for row in rows:
        w.writerow([_cell(row.get(c)) for c in columns])
    return buf.getvalue()


def table_markdown(columns: Sequence[str], rows: Sequence[dict[str, Any]]) -> str:
    """Rows as a GitHub Markdown table (pipes escaped, newlines flattened)."""

    def esc(v: Any) -> str:
        return _cell(v).replace("\n", " ").replace("|", "\\|")

    lines = ["| " + " | ".join(columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
    lines += ["| " + " | ".join(esc(r.get(c)) for c in columns) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def one_line(text: str, limit: int = MAX_ERROR_CHARS) -> str:
    """An error text as one line of at most `limit` characters."""
    flat = " ".join(str(text).split())
    return flat if len(flat) <= limit else flat[: limit - 3] + "..."


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def config_payload(config: Config) -> dict[str, Any]:
    """The config as plain data for a worker, which validates it again (`worker_config`):
    a worker whose uwbfuse differs in a field gets its own defaults or a clear error,
    rather than a pickled model of another version."""
    return config.model_dump(mode="json")


def worker_config(payload: dict[str, Any]) -> Config:
    """The `Config` a worker runs with, from `config_payload` (raises ConfigError)."""
    return config_from_dict(payload, "config sent by the client")


def config_digest(config: Config) -> str:
    """Digest of the effective configuration (its dumped TOML)."""
    return sha256_bytes(dump_config(config).encode("utf-8"))


def uwbfuse_version() -> str:
    try:
        return importlib.metadata.version("uwbfuse")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


# --------------------------------------------------------------------------------------
# The cluster


class ClusterKind(StrEnum):
    """Where jobs ran."""

    LOCAL = "local"  # an in-process LocalCluster started for the jobs
    REMOTE = "remote"  # an existing scheduler (--scheduler)
    INLINE = "inline"  # no dask installed: one after another in this process
    NONE = "none"  # nothing to run (every job resumed)


@dataclass(frozen=True)
class ClusterInfo:
    """Where the jobs run: kind, scheduler address, workers, dashboard link."""

    kind: ClusterKind
    scheduler: str
    n_workers: int
    dashboard: str | None = None


def describe_cluster(info: ClusterInfo, dashboard: bool = False) -> str:
    """One line saying where the jobs run (and the dashboard link, if asked for)."""
    if info.kind is ClusterKind.INLINE:
        line = "running in this process (dask.distributed not installed)"
    else:
        where = "local Dask cluster" if info.kind is ClusterKind.LOCAL else "Dask cluster"
        line = f"{where} {info.scheduler}, {info.n_workers} worker(s)"
    if dashboard:
        line += f"; dashboard: {info.dashboard or 'not available (needs bokeh>=3.1)'}"
    return line


def _import_distributed() -> Any:
    try:
        import distributed
    except ImportError:
        return None
    return distributed


def local_worker_count(n_jobs: int, workers: int | None = None) -> int:
    """Worker processes of the default LocalCluster: `workers`, else one per usable core,
    never more than there are jobs."""
    if workers is not None:
        if workers < 1:
            raise FleetError(f"--workers must be at least 1, got {workers}")
        return workers
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, n_jobs))


@contextmanager
def cluster(
    scheduler: str | None = None,
    workers: int | None = None,
    dashboard: bool = False,
    n_jobs: int = 1,
) -> Iterator[tuple[Any, ClusterInfo]]:
    """Yield `(client, info)`: a Dask client on a fresh LocalCluster (no address) or on the
    scheduler at `scheduler`; `(None, info)` with kind "inline" when dask is absent and no
    address is given. Everything started here is closed on exit."""
    distributed = _import_distributed()
    if distributed is None:
        if scheduler:
            raise FleetError(
                f"--scheduler {scheduler} needs dask.distributed: "
                "pip install 'uwbfuse[fleet]' (or 'dask[distributed]')"
            )
        log.warning("dask.distributed is not installed: running the jobs one by one here")
        yield None, ClusterInfo(ClusterKind.INLINE, "", 1)
        return

    if scheduler:
        if workers is not None:
            log.warning("--workers %d ignored: the cluster at %s has its own", workers, scheduler)
        try:
            client = distributed.Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except ValueError as e:  # no port, unknown scheme, ...
            raise FleetError(f"bad Dask scheduler address {scheduler!r}: {e}") from None
        except (OSError, TimeoutError) as e:
            raise FleetError(f"cannot reach the Dask scheduler at {scheduler}: {e}") from None
        try:
            try:
                client.wait_for_workers(1, timeout=WORKER_WAIT_S)
            except TimeoutError:
                raise FleetError(
                    f"the Dask scheduler at {scheduler} has no workers "
                    f"(waited {WORKER_WAIT_S:.0f} s; start some with 'dask worker {scheduler}')"
                ) from None
            _check_worker_versions(client, scheduler)
            info = ClusterInfo(
                ClusterKind.REMOTE, scheduler, len(client.scheduler_info()["workers"]),
                client.dashboard_link if dashboard else None,
            )
            yield client, info
        finally:
            client.close()
        return

    import dask

    n = local_worker_count(n_jobs, workers)
    # The workers' statistical profiler costs ~7 % CPU on long jobs and only feeds the
    # dashboard: keep it for --dashboard.
    try:
        with dask.config.set({"distributed.worker.profile.enabled": dashboard}):
            local = distributed.LocalCluster(
                n_workers=n,
                threads_per_worker=1,
                processes=True,
                host="127.0.0.1",
                # Without --dashboard the scheduler's HTTP server still runs: on a free port.
                dashboard_address=":8787" if dashboard else "127.0.0.1:0",
                scheduler_kwargs={"dashboard": dashboard},
                silence_logs=logging.ERROR,
            )
    except OSError as e:
        raise FleetError(f"cannot start a local Dask cluster: {e}") from None
    try:
        client = distributed.Client(local)
        try:
            link = client.dashboard_link if dashboard else None
            yield client, ClusterInfo(ClusterKind.LOCAL, local.scheduler_address, n, link)
        finally:
            client.close()
    finally:
        local.close()


def _check_worker_versions(client: Any, scheduler: str) -> None:
    """Fail early when a worker cannot import uwbfuse; warn when its version differs."""
    mine = uwbfuse_version()
    versions = client.run(importlib.metadata.version, "uwbfuse", on_error="return")
    missing = [w for w, v in versions.items() if isinstance(v, BaseException)]
    if missing:
        raise FleetError(
            f"worker {missing[0]} of {scheduler} has no uwbfuse installed "
            "(install the same uwbfuse version on every worker)"
        )
    other = {w: v for w, v in versions.items() if v != mine}
    if other:
        w, v = next(iter(other.items()))
        log.warning("worker %s runs uwbfuse %s, this client %s", w, v, mine)


@dataclass(frozen=True)
class Job:
    """One task: `fn(arg)` on a worker. `fn` must be importable there (module level)."""

    name: str
    fn: Callable[[Any], Any]
    arg: Any


ResultFn = Callable[[Job, Any, BaseException | None], None]
"""`on_result(job, value, error)`: called in the client as each job ends, in end order;
`error` is set (and `value` None) when the task itself could not complete."""


def run_jobs(
    jobs: Sequence[Job],
    on_result: ResultFn,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    dashboard: bool = False,
    on_start: Callable[[ClusterInfo], None] | None = None,
    progress: ProgressFn | None = None,
    done_before: int = 0,
) -> ClusterInfo:
    """Run `jobs` on a cluster (see `cluster`), one task each, and hand every outcome to
    `on_result` as it arrives. `progress(done, total, note)` counts `done_before` jobs
    (skipped on resume) as already done. Returns where the jobs ran."""
    total = done_before + len(jobs)
    if not jobs:
        if progress is not None:
            progress(done_before, total, "resumed")
        return ClusterInfo(ClusterKind.NONE, "", 0)
    with cluster(scheduler, workers, dashboard, n_jobs=len(jobs)) as (client, info):
        if on_start is not None:
            on_start(info)
        if progress is not None:
            progress(done_before, total, f"{done_before} resumed" if done_before else "")
        done = done_before
        if client is None:
            for job in jobs:
                on_result(job, job.fn(job.arg), None)
                done += 1
                if progress is not None:
                    progress(done, total, job.name)
            return info

        token = uuid.uuid4().hex[:8]
        futures = {}
        for job in jobs:
            fut = client.submit(job.fn, job.arg, key=f"uwbfuse-{job.name}-{token}", pure=False)
            futures[fut] = job
        for fut in _completed(client, list(futures), info):
            job = futures.pop(fut)
            try:
                value = fut.result()
            except Exception as e:  # KilledWorker (its worker died too often), cancelled
                if client.status not in ("running", "connecting"):
                    raise FleetError(
                        f"lost the Dask scheduler {info.scheduler} ({type(e).__name__}); "
                        f"{len(futures) + 1} jobs unfinished: run again to resume"
                    ) from None
                log.warning("job %s did not complete: %s", job.name, e)
                on_result(job, None, e)
            else:
                on_result(job, value, None)
            fut.release()
            done += 1
            if progress is not None:
                progress(done, total, job.name)
        return info


def _completed(client: Any, futures: list[Any], info: ClusterInfo) -> Iterator[Any]:
    """Yield futures as they finish; raise FleetError when the cluster has had no worker
    for `WORKER_WAIT_S` (tasks would wait forever)."""
    from concurrent.futures import CancelledError

    from distributed import wait

    pending = set(futures)
    alone_since: float | None = None
    while pending:
        try:
            wait(list(pending), timeout=POLL_S, return_when="FIRST_COMPLETED")
        except (TimeoutError, CancelledError):  # cancelled: their result() says so
            pass
        done = {f for f in pending if f.status in ("finished", "error", "cancelled")}
        pending -= done
        yield from done
        if done:
            alone_since = None
            continue
        if client.status not in ("running", "connecting"):
            raise FleetError(
                f"lost the Dask scheduler {info.scheduler}; {len(pending)} jobs unfinished: "
                "run again to resume"
            )
        if client.nthreads():
            alone_since = None
        elif alone_since is None:
            alone_since = time.monotonic()
        elif time.monotonic() - alone_since > WORKER_WAIT_S:
            client.cancel(list(pending))
            raise FleetError(
                f"no Dask workers left at {info.scheduler} for {WORKER_WAIT_S:.0f} s; "
                f"{len(pending)} jobs unfinished: run again to resume"
            )


# --------------------------------------------------------------------------------------
# Batch: one method over many logs


@dataclass(frozen=True)
class BatchJobSpec:
    """What a worker needs to run one log: everything by value except the log itself."""

    name: str
    log: str
    method: Method
    config: dict[str, Any]  # config_payload(): validated again on the worker
    config_sha256: str


@dataclass
class BatchJobOutput:
    """What a worker sends back: the metrics row, the TUM bytes (None when failed) and,
    for unexpected exceptions, the traceback."""

    row: dict[str, Any]
    tum: bytes | None
    traceback: str | None = None
    fingerprint: list[int] | None = None


def log_fingerprint(path: str | Path) -> list[int] | None:
    """[total bytes, latest mtime in ns] of a log file or rosbag2 directory, None if
    unreachable from here."""
    p = Path(path)
    try:
        if p.is_dir():
            files = [f for f in p.rglob("*") if f.is_file()]
            stats = [f.stat() for f in files]
            return [sum(s.st_size for s in stats), max((s.st_mtime_ns for s in stats), default=0)]
        st = p.stat()
    except OSError:
        return None
    return [st.st_size, st.st_mtime_ns]


def ate_alignment(method: Method) -> str:
    """Alignment for the batch ATE: none (map frame) for every method that uses ranges;
    se2 for dead reckoning (`imu`, `odom`), which cannot know its start pose."""
    return "none" if method.uses_ranges else "se2"


def ate_metrics(
    trajectory: PoseStream, ground_truth: PoseStream | None, align: str
) -> tuple[dict[str, Any], str]:
    """ATE RMSE in the plane and in 3-D (m) of `trajectory` against `ground_truth` after
    `align`, as `uwbfuse.eval.evaluate` gives them (and `compare` reports them); empty
    with the reason when it cannot score."""
    if ground_truth is None or len(ground_truth) == 0:
        return {}, ""
    from uwbfuse.eval import evaluate

    try:
        result = evaluate(trajectory, ground_truth, align=align)
    except UwbfuseError as e:
        return {}, one_line(f"ATE: {e}")
    return {
        "ate2d_rmse_m": float(result.ate_2d.rmse), "ate3d_rmse_m": float(result.ate_3d.rmse),
        "ate_align": align,
    }, ""


def run_batch_job(spec: BatchJobSpec) -> BatchJobOutput:
    """Worker side of one batch job: read the log, estimate, write TUM bytes, score.

    The same steps as `pipeline.run_log` (so the TUM is identical); never raises for a bad
    log or a failing method: the row says status "failed" and why.
    """
    from uwbfuse.pipeline import estimate

    tic = time.perf_counter()
    cpu0 = time.thread_time()
    row: dict[str, Any] = {
        "log": spec.log, "status": "failed", "error": "",
        "host": f"{socket.gethostname()}:{os.getpid()}",
    }
    fingerprint = log_fingerprint(spec.log)
    try:
        from uwbfuse.io.reader import read_log
        from uwbfuse.io.tum import write_tum

        config = worker_config(spec.config)
        sensor_log = read_log(spec.log, config)
        read_s = time.perf_counter() - tic
        res = estimate(sensor_log, spec.method, config)
        res.read_wall_s = read_s
        with tempfile.TemporaryDirectory(prefix="uwbfuse-batch-") as d:
            tmp = Path(d) / "est.tum"
            write_tum(tmp, res.trajectory)
            tum = tmp.read_bytes()
        ate, note = ate_metrics(
            res.trajectory, sensor_log.ground_truth, ate_alignment(spec.method)
        )
        row.update(ate)
        row.update(
            status="ok", error=note, duration_s=res.log_duration_s, poses=len(res.trajectory),
            read_s=read_s, estimate_s=res.estimate_wall_s,
            realtime_factor=res.realtime_factor,
            skipped=sum(sensor_log.report.skipped.values()),
        )
        row.update(wall_s=time.perf_counter() - tic, cpu_s=time.thread_time() - cpu0)
        return BatchJobOutput(row, tum, None, fingerprint)
    except UwbfuseError as e:
        row.update(error=one_line(str(e)), wall_s=time.perf_counter() - tic)
        return BatchJobOutput(row, None, None, fingerprint)
    except Exception as e:
        log.exception("%s: method %s crashed", spec.log, spec.method.value)
        row.update(error=one_line(f"{type(e).__name__}: {e}"), wall_s=time.perf_counter() - tic)
        return BatchJobOutput(row, None, traceback.format_exc(), fingerprint)


@dataclass
class BatchResult:
    """What `batch_run` did: one row per log (input order) and where the files are."""

    rows: list[dict[str, Any]]
    out_dir: Path
    summary_csv: Path
    summary_md: Path
    cluster: ClusterInfo
    wall_s: float
    columns: tuple[str, ...] = SUMMARY_COLUMNS

    @property
    def n_ok(self) -> int:
        return sum(r["status"] == "ok" for r in self.rows)

    @property
    def n_failed(self) -> int:
        return len(self.rows) - self.n_ok

    @property
    def n_resumed(self) -> int:
        return sum(bool(r.get("resumed")) for r in self.rows)

    def table(self, columns: Sequence[str] | None = None) -> str:
        """The summary as a Markdown table (for the terminal)."""
        return table_markdown(columns or self.columns, self.rows)


def job_names(logs: Sequence[str]) -> list[str]:
    """A file-name-safe, unique name per log: its stem (`agv1.mcap` -> `agv1`, a rosbag2
    directory -> its name), with a short path digest where two stems collide."""
    stems = []
    for lg in logs:
        name = Path(lg.rstrip("/")).name.removesuffix(".mcap") or "log"
        stems.append("".join(c if c.isalnum() or c in "-_." else "_" for c in name))
    out = []
    for lg, stem in zip(logs, stems, strict=True):
        if stems.count(stem) > 1:
            stem = f"{stem}-{hashlib.sha1(lg.encode()).hexdigest()[:8]}"
        out.append(stem)
    return out


def _resolve_log(path: str) -> str:
    """Absolute path (workers may run elsewhere); URLs are kept as given."""
    if "://" in path:
        return path
    return str(Path(path).expanduser().absolute())


def _done_path(out: Path, name: str, method: Method) -> Path:
    return out / f"{name}.{method.value}.json"


def _tum_path(out: Path, name: str, method: Method) -> Path:
    return out / f"{name}.{method.value}.tum"


def _completed_row(spec: BatchJobSpec, out: Path) -> dict[str, Any] | None:
    """The stored row of a job whose outputs exist and are complete, else None."""
    done = _done_path(out, spec.name, spec.method)
    try:
        marker = json.loads(done.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(marker, dict) or marker.get("format") != DONE_FORMAT:
        return None
    same = (
        marker.get("log") == spec.log
        and marker.get("method") == spec.method.value
        and marker.get("config_sha256") == spec.config_sha256
        and marker.get("row", {}).get("status") == "ok"
    )
    if not same:
        return None
    now = log_fingerprint(spec.log)
    if now is not None and marker.get("fingerprint") not in (None, now):
        return None
    try:
        tum = _tum_path(out, spec.name, spec.method).read_bytes()
    except OSError:
        return None
    if sha256_bytes(tum) != marker.get("tum_sha256"):
        return None
    return dict(marker["row"])


def _store_output(spec: BatchJobSpec, out: Path, output: BatchJobOutput) -> dict[str, Any]:
    """Write a job's TUM then its done marker (last); return the summary row."""
    row = dict(output.row)
    tum_path = _tum_path(out, spec.name, spec.method)
    marker: dict[str, Any] = {
        "format": DONE_FORMAT, "log": spec.log, "method": spec.method.value,
        "config_sha256": spec.config_sha256, "fingerprint": output.fingerprint,
        "uwbfuse": uwbfuse_version(), "tum_sha256": None,
    }
    if row["status"] == "ok" and output.tum is not None:
        write_atomic(tum_path, output.tum)
        row["tum"] = tum_path.name
        marker["tum_sha256"] = sha256_bytes(output.tum)
    else:
        tum_path.unlink(missing_ok=True)  # a stale trajectory from an earlier run
    if output.traceback:
        marker["traceback"] = output.traceback
    marker["row"] = row
    write_atomic(_done_path(out, spec.name, spec.method), json.dumps(marker, indent=1) + "\n")
    return row


def batch_run(
    logs: Sequence[str | Path],
    method: str | Method,
    config_path: str | Path | None = None,
    out_dir: str | Path = "batch_out",
    scheduler: str | None = None,
    *,
    workers: int | None = None,
    dashboard: bool = False,
    resume: bool = True,
    progress: ProgressFn | None = None,
    on_start: Callable[[ClusterInfo], None] | None = None,
) -> BatchResult:
    """Run `method` on every log as one Dask task each; write trajectories, done markers,
    the effective config and the summary under `out_dir`; return the rows.

    `scheduler`: address of an existing Dask scheduler (`tcp://host:8786`), or None for an
    in-process LocalCluster of `workers` processes (default: one per core). `resume`: skip
    logs whose outputs under `out_dir` are complete for the same log, method and config.
    `on_start(info)` is called once the cluster is up (e.g. to show the dashboard link).
    A failing log fails its own row; only cluster or output-directory problems raise
    (`FleetError`), as do a bad config (`ConfigError`) and an unknown method.
    """
    tic = time.perf_counter()
    m = Method(method)
    config = load_config(config_path)
    out = Path(out_dir)
    sha = config_digest(config)
    resolved = [_resolve_log(str(lg)) for lg in logs]
    unique = list(dict.fromkeys(resolved))
    if len(unique) < len(resolved):
        log.warning("%d logs given more than once: each runs once", len(resolved) - len(unique))
    specs = [
        BatchJobSpec(name, lg, m, config_payload(config), sha)
        for name, lg in zip(job_names(unique), unique, strict=True)
    ]
    write_atomic(out / "config.toml", dump_config(config))

    rows: dict[str, dict[str, Any]] = {}
    pending: list[Job] = []
    for spec in specs:
        row = _completed_row(spec, out) if resume else None
        if row is not None:
            row["resumed"] = True
            rows[spec.name] = row
        else:
            pending.append(Job(spec.name, run_batch_job, spec))
    if rows:
        log.info("resume: %d of %d logs already done in %s", len(rows), len(specs), out)

    def on_result(job: Job, value: Any, error: BaseException | None) -> None:
        spec: BatchJobSpec = job.arg
        if error is not None:
            value = BatchJobOutput(
                {"log": spec.log, "status": "failed",
                 "error": one_line(f"task lost: {type(error).__name__}: {error}")},
                None,
            )
        row = _store_output(spec, out, value)
        row["resumed"] = False
        rows[spec.name] = row

    info = run_jobs(
        pending, on_result, scheduler=scheduler, workers=workers, dashboard=dashboard,
        on_start=on_start, progress=progress, done_before=len(rows),
    )
    ordered = [rows[s.name] for s in specs]
    result = BatchResult(
        ordered, out, out / "summary.csv", out / "summary.md", info,
        time.perf_counter() - tic,
    )
    write_atomic(result.summary_csv, table_csv(SUMMARY_COLUMNS, ordered))
    write_atomic(result.summary_md, table_markdown(SUMMARY_COLUMNS, ordered))
    return result
