# SPDX-License-Identifier: BSD-3-Clause
"""The `uwbfuse` command line: parses arguments and calls one library function per command.

Known errors (`UwbfuseError`) become one line on stderr and exit status 2; heavy imports
happen inside the commands so `uwbfuse --help` stays fast.
"""

from __future__ import annotations

import argparse
import logging
import logging.handlers
import os
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from uwbfuse.constants import LABEL_THRESHOLD_M, NLOS_EXCESS_LAWS
from uwbfuse.errors import SimulationError, UwbfuseError

if TYPE_CHECKING:
    from uwbfuse.progress import ProgressBar

EXAMPLES = """examples:
  uwbfuse simulate warehouse.mcap --scenario warehouse --duration 120 --seed 1
  uwbfuse run warehouse.mcap --method isam2 -o est.tum
  uwbfuse eval est.tum --gt warehouse.mcap
  uwbfuse compare warehouse.mcap --methods isam2,batch,ekf --out results/
  uwbfuse simulate fleet.mcap --scenario warehouse-fleet --duration 60
  uwbfuse collisions fleet.agv0.mcap fleet.agv1.mcap --method isam2 --out coll/
  uwbfuse dump-config > uwbfuse.toml
"""

METHOD_HELP = "isam2 | isam2-smoothed | batch | ekf | ukf | wls | lkf | imu | odom"
SCHEDULER_HELP = "Dask scheduler, e.g. tcp://10.0.0.5:8786 (default: a local cluster)"
WORKERS_HELP = "worker processes of the local cluster (default: one per core)"
DASHBOARD_HELP = "serve and print the Dask dashboard address"
CONFIG_HELP = "TOML configuration (default: built-in defaults; see `uwbfuse dump-config`)"
PROGRESS_HELP = ("progress bar on stderr (default: only when stderr is a terminal)")


class _HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Help with each option's default, as ArgumentDefaultsHelpFormatter, except where the
    help already says its default or there is none to say (None, a False flag)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if ("default" in text or action.default in (None, False, argparse.SUPPRESS)
                or action.required or not action.option_strings):
            return text
        return f"{text} (default: %(default)s)"


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("uwbfuse")
    except PackageNotFoundError:
        return "unknown (not installed)"


def _cmd_simulate(args: argparse.Namespace) -> int:
    from uwbfuse.io.writer import write_contract_log
    from uwbfuse.sim.fleet import get_fleet
    from uwbfuse.sim.simulator import simulate

    if get_fleet(args.scenario) is not None:
        if args.nlos_excess != NLOS_EXCESS_LAWS[0]:
            raise SimulationError("--nlos-excess applies to single-vehicle scenarios only")
        return _simulate_fleet(args)

    extra: dict[str, object] = {"nlos_excess": args.nlos_excess}
    if args.signal_quality:
        extra["signal_quality"] = True
    sim = simulate(args.scenario, duration_s=args.duration, seed=args.seed, **extra)
    write_contract_log(args.out, sim)
    span = sim.time_span_ns()
    print(
        f"wrote {args.out}: scenario {args.scenario}, {(span[1] - span[0]) / 1e9:.1f} s, "
        f"{len(sim.imu or [])} imu, {len(sim.wheel or [])} wheel, "
        f"{len(sim.ranges or [])} ranges, {len(sim.anchors or [])} anchors"
    )
    return 0


def _simulate_fleet(args: argparse.Namespace) -> int:
    from uwbfuse.sim.fleet import write_fleet

    sims, files = write_fleet(args.out, args.scenario, args.duration, args.seed)
    print(f"wrote {len(sims)} logs: scenario {args.scenario}, {args.duration:.1f} s, "
          "one per AGV on a common clock")
    for (name, res), path in zip(sims, files, strict=False):
        print(f"  {name}: {path} (starts after {res.scenario.still_start_s:.1f} s)")
    print(f"  map: {files[-1]} (the [map] for uwbfuse collisions on TUM files)")
    return 0


def _default_tum_path(log_path: str, method: str) -> Path:
    stem = Path(log_path.rstrip("/")).name.removesuffix(".mcap").removesuffix(".db3")
    return Path(f"{stem}.{method}.tum")


def _progress(args: argparse.Namespace, label: str) -> ProgressBar:
    """A time-based bar on stderr: on when stderr is a terminal, or as --progress says."""
    from uwbfuse.progress import ProgressBar

    on = args.progress if args.progress is not None else sys.stderr.isatty()
    return ProgressBar(label, unit="s of log", enabled=on)


def _cmd_run(args: argparse.Namespace) -> int:
    from uwbfuse.config import load_config
    from uwbfuse.estimator import Method
    from uwbfuse.pipeline import run_log
    from uwbfuse.report import run_summary

    config = load_config(args.config)
    method = Method(args.method)
    out = Path(args.output) if args.output else _default_tum_path(args.log, method.value)
    with _progress(args, method.value) as bar:
        res = run_log(args.log, method, config, tum_out=out, mcap_out=args.mcap_out,
                      cov_out=args.cov_out, progress=bar, report_out=args.report)
    for line in res.read_report.lines():
        print(f"read: {line}", file=sys.stderr)
    outputs = {k: str(v) for k, v in (("tum", out), ("mcap", args.mcap_out),
                                       ("cov", args.cov_out), ("report", args.report)) if v}
    for line in run_summary(res, outputs):
        print(line)
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    from uwbfuse.eval.command import evaluate_files, export_ground_truth

    if args.save_gt:
        n = export_ground_truth(args.gt, args.save_gt, config_path=args.config)
        print(f"wrote {args.save_gt}: {n} ground-truth poses (TUM, base frame in map frame)")
    if args.est is None:
        if not args.save_gt:
            raise UwbfuseError("EST.tum is required (unless --save-gt is given)")
        return 0
    result = evaluate_files(
        args.est, args.gt, config_path=args.config, align=args.align, max_dt=args.max_dt
    )
    print(result.table())
    if args.json:
        result.write_json(args.json)
    return 0


def _cmd_train_nlos(args: argparse.Namespace) -> int:
    from uwbfuse.train_nlos import train_nlos

    res = train_nlos(args.logs, args.output, config_path=args.config, gts=args.gt,
                     n_trees=args.trees, threshold=args.threshold, seed=args.seed)
    print(f"wrote {args.output}: random forest of {args.trees} trees on {res.n_ranges} "
          f"ranges ({res.n_nlos} NLOS, |error| > {args.threshold} m; {res.n_unlabelled} "
          f"outside the ground truth skipped), features {', '.join(res.features)}")
    return 0


def _cmd_calibrate_nlos(args: argparse.Namespace) -> int:
    from uwbfuse.positioning.nlos_weighting import calibrate_nlos_file

    text = calibrate_nlos_file(args.log, config_path=args.config, gt_path=args.gt)
    if args.output:
        from uwbfuse.compare import write_text_atomic

        write_text_atomic(Path(args.output), text)
        print(f"wrote {args.output}")
    else:
        sys.stdout.write(text)
    return 0


def _cmd_dump_config(args: argparse.Namespace) -> int:
    from uwbfuse.config import dump_config

    sys.stdout.write(dump_config())
    return 0


def _cmd_compare(args: argparse.Namespace) -> int:
    from uwbfuse.compare import compare_log

    with _progress(args, "compare") as bar:
        result = compare_log(
            args.log, methods=args.methods, config_path=args.config, out_dir=args.out,
            gt_path=args.gt, align=args.align, html=args.html, progress=bar,
        )
    print(result.markdown(), end="")
    print(f"wrote {len(result.files)} files to {result.out_dir}/")
    return 0 if any(r.status == "ok" for r in result.rows) else 2


def _quiet_dask(args: argparse.Namespace) -> None:
    """Dask logs its start-up at INFO (set when it is imported); keep that for -v only."""
    if args.verbose:
        return
    try:
        import distributed  # noqa: F401 (its import installs the logger levels we lower)
    except ImportError:
        return
    logging.getLogger("distributed").setLevel(logging.ERROR)


def _print_cluster(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _cmd_montecarlo(args: argparse.Namespace) -> int:
    from uwbfuse.fleet import describe_cluster
    from uwbfuse.montecarlo import montecarlo
    from uwbfuse.progress import ProgressBar

    _quiet_dask(args)
    with ProgressBar("runs") as bar:
        result = montecarlo(
            scenario=args.scenario, runs=args.runs, duration_s=args.duration,
            methods=args.methods, out_dir=args.out, scheduler=args.scheduler,
            workers=args.workers, dashboard=args.dashboard, progress=bar,
            on_start=lambda info: _print_cluster(describe_cluster(info, args.dashboard)),
        )
    print(result.table())
    print(f"wrote {result.out_dir}/montecarlo.csv, montecarlo.md, runs.csv "
          f"({result.wall_s:.1f} s)")
    return 0


def _cmd_batch(args: argparse.Namespace) -> int:
    from uwbfuse.fleet import batch_run, describe_cluster
    from uwbfuse.progress import ProgressBar

    _quiet_dask(args)
    with ProgressBar("logs") as bar:
        result = batch_run(
            args.logs, method=args.method, config_path=args.config, out_dir=args.out_dir,
            scheduler=args.scheduler, workers=args.workers, dashboard=args.dashboard,
            progress=bar,
            on_start=lambda info: _print_cluster(describe_cluster(info, args.dashboard)),
        )
    print(result.table(("log", "status", "duration_s", "poses", "ate2d_rmse_m", "wall_s",
                        "realtime_factor", "skipped", "error")))
    print(f"{result.n_ok} of {len(result.rows)} logs ok ({result.n_resumed} resumed) in "
          f"{result.wall_s:.1f} s; summary: {result.summary_csv}, {result.summary_md}")
    if result.n_failed:
        print(f"uwbfuse batch: error: {result.n_failed} of {len(result.rows)} logs failed "
              f"(see {result.summary_csv})", file=sys.stderr)
        return 2
    return 0


def _cmd_collisions(args: argparse.Namespace) -> int:
    from uwbfuse.safety.command import collisions

    _quiet_dask(args)
    res = collisions(
        args.inputs, args.config, names=args.names.split(",") if args.names else None,
        out_dir=args.out, method=args.method,
        cov_paths=args.cov.split(",") if args.cov is not None else None,
        scheduler=args.scheduler, workers=args.workers,
    )
    print(res.table(), end="")
    n_col = sum(e["kind"] == "collision" for e in res.events)
    print(f"{len(res.tracks)} vehicles, map from {res.map_source}: {len(res.events)} events "
          f"({n_col} collision, {len(res.events) - n_col} warning epochs) in "
          f"{res.wall_s:.1f} s; wrote {', '.join(str(f) for f in res.files)}")
    return 0


def _add_simulate(sub: argparse._SubParsersAction) -> None:
    """`uwbfuse simulate`: write a simulated contract log."""
    s = sub.add_parser("simulate", help="write a simulated contract log (MCAP)")
    s.add_argument("out", metavar="OUT.mcap", help="MCAP log to write")
    s.add_argument("--scenario", default="warehouse", help="room | warehouse | factory | ...")
    s.add_argument("--duration", type=float, default=120.0, help="log length, s")
    s.add_argument("--seed", type=int, default=0, help="random seed (same seed, same log)")
    s.add_argument("--signal-quality", action="store_true",
                   help="ranges with RX and first-path power (dBm) on a custom range type "
                   "(uwbfuse_msgs/msg/UwbRange), named in the log's uwb_fields metadata")
    s.add_argument("--nlos-excess", choices=NLOS_EXCESS_LAWS, default=NLOS_EXCESS_LAWS[0],
                   help="law of the NLOS excess range: gaussian (Qiu 2022's fitted "
                   "N(mean, std), reads short about one NLOS range in five) or lognormal "
                   "(the same mean and std, never negative); single-vehicle scenarios")
    s.set_defaults(func=_cmd_simulate)


def _add_run(sub: argparse._SubParsersAction) -> None:
    """`uwbfuse run`: estimate one log with one method."""
    r = sub.add_parser("run", help="estimate a trajectory from a log")
    r.add_argument("log", metavar="LOG", help=".mcap file or rosbag2 directory")
    r.add_argument("--method", required=True, help=METHOD_HELP)
    r.add_argument("--config", metavar="FILE", help=CONFIG_HELP)
    r.add_argument("-o", "--output", metavar="EST.tum",
                   help="TUM trajectory to write (default: <log>.<method>.tum)")
    r.add_argument("--mcap-out", metavar="EST.mcap",
                   help="also write a ROS 2 MCAP: pose, pose with covariance, /tf, anchors")
    r.add_argument("--cov-out", metavar="FILE.csv",
                   help="also write each pose's 6x6 covariance (t, then 36 entries row-major)")
    r.add_argument("--report", metavar="FILE.json",
                   help="also write the full run diagnostics as JSON")
    r.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                   help=PROGRESS_HELP)
    r.set_defaults(func=_cmd_run)


def _add_eval(sub: argparse._SubParsersAction) -> None:
    """`uwbfuse eval`: score a TUM trajectory against ground truth."""
    e = sub.add_parser("eval", help="score a TUM trajectory against ground truth")
    e.add_argument("est", metavar="EST.tum", nargs="?",
                   help="estimated trajectory (optional with --save-gt)")
    e.add_argument("--gt", required=True, metavar="GT.tum|LOG",
                   help="ground truth: a TUM file, or a log with a ground-truth topic")
    e.add_argument("--config", metavar="FILE", help="topics, when --gt is a log")
    e.add_argument("--save-gt", metavar="GT.tum",
                   help="write the ground truth of --gt as TUM (for evo)")
    e.add_argument("--align", default="none", choices=["none", "se2", "se3"],
                   help="align the estimate to the ground truth first (for GT in another frame)")
    e.add_argument("--max-dt", type=float, default=0.02, help="association tolerance, s")
    e.add_argument("--json", metavar="FILE", help="also write the metrics as JSON")
    e.set_defaults(func=_cmd_eval)


def _add_compare(sub: argparse._SubParsersAction) -> None:
    """`uwbfuse compare`: several methods on one log, table and plots."""
    c = sub.add_parser("compare", help="run several methods on one log: table and plots")
    c.add_argument("log", metavar="LOG", help=".mcap file or rosbag2 directory")
    c.add_argument("--methods", default="isam2,batch,ekf,ukf,wls,imu,odom",
                   help="comma-separated methods to run")
    c.add_argument("--config", metavar="FILE", help=CONFIG_HELP)
    c.add_argument("--out", default="compare_out", metavar="DIR",
                   help="folder for the table, trajectories and plots")
    c.add_argument("--gt", metavar="GT.tum", help="ground truth when the log has none")
    c.add_argument("--align", default="none", choices=["none", "se2", "se3"],
                   help="align each estimate to a ground truth in another frame")
    c.add_argument("--html", action="store_true",
                   help="also write DIR/report.html: table, plots and config in one file")
    c.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                   help=PROGRESS_HELP)
    c.set_defaults(func=_cmd_compare)


def _add_montecarlo(sub: argparse._SubParsersAction) -> None:
    """`uwbfuse montecarlo`: simulated runs over seeds."""
    m = sub.add_parser("montecarlo", help="repeat simulated runs over seeds")
    m.add_argument("--scenario", default="warehouse", help="room | warehouse | factory | ...")
    m.add_argument("--runs", type=int, default=20, help="simulated runs (seeds 0..N-1)")
    m.add_argument("--duration", type=float, default=200.0, help="length of each run, s")
    m.add_argument("--methods", default="isam2,ekf,imu", help="comma-separated methods to run")
    m.add_argument("--out", default="montecarlo_out", metavar="DIR",
                   help="folder for the tables and per-run results")
    m.add_argument("--scheduler", metavar="ADDRESS", help=SCHEDULER_HELP)
    m.add_argument("--workers", type=int, metavar="N", help=WORKERS_HELP)
    m.add_argument("--dashboard", action="store_true", help=DASHBOARD_HELP)
    m.set_defaults(func=_cmd_montecarlo)


def _add_batch(sub: argparse._SubParsersAction) -> None:
    """`uwbfuse batch`: one method over many logs."""
    b = sub.add_parser("batch", help="run one method over many logs")
    b.add_argument("logs", nargs="+", metavar="LOG", help=".mcap files or rosbag2 directories")
    b.add_argument("--method", required=True, help=METHOD_HELP)
    b.add_argument("--config", metavar="FILE", help=CONFIG_HELP)
    b.add_argument("--out-dir", default="batch_out", metavar="DIR",
                   help="folder for one trajectory per log and the summary table")
    b.add_argument("--scheduler", metavar="ADDRESS", help=SCHEDULER_HELP)
    b.add_argument("--workers", type=int, metavar="N", help=WORKERS_HELP)
    b.add_argument("--dashboard", action="store_true", help=DASHBOARD_HELP)
    b.set_defaults(func=_cmd_batch)


def _add_calibrate_nlos(sub: argparse._SubParsersAction) -> None:
    """`uwbfuse calibrate-nlos`: fit the LOS/NLOS range-error model."""
    n = sub.add_parser(
        "calibrate-nlos",
        help="fit the per-range LOS/NLOS range-error model (Qiu 2022 eq. 8-9) for [nlos]",
    )
    n.add_argument("log", metavar="LOG", help="calibration log with ground truth")
    n.add_argument("--config", metavar="FILE", help=CONFIG_HELP)
    n.add_argument("--gt", metavar="GT.tum", help="ground truth, if not in the log")
    n.add_argument("-o", "--output", metavar="OUT.toml", help="default: stdout")
    n.set_defaults(func=_cmd_calibrate_nlos)


def _add_train_nlos(sub: argparse._SubParsersAction) -> None:
    """`uwbfuse train-nlos`: train the NLOS random forest."""
    tn = sub.add_parser(
        "train-nlos", help="train the NLOS random-forest classifier for [nlos] classifier",
        description="Label every range LOS or NLOS from ground truth (|measured - true "
        "range| > --threshold) and train a random forest on causal per-range features "
        "(residual against a causal fix, range jump and rate, distance, anchor elevation, "
        "RSSI and RX - first-path power where the log has them). The model file is skops "
        "data (never a pickle).",
        epilog="example:\n  uwbfuse train-nlos a.mcap b.mcap -o nlos.skops\n  uwbfuse "
        "train-nlos real.mcap --gt gt.tum --config c.toml -o nlos.skops",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    tn.add_argument("logs", nargs="+", metavar="LOG", help="logs with ground truth")
    tn.add_argument("--config", metavar="FILE", help=CONFIG_HELP)
    tn.add_argument("--gt", nargs="+", metavar="GT.tum",
                    help="ground truth per log (TUM, same order), else the log's topic")
    tn.add_argument("-o", "--output", required=True, metavar="MODEL", help="model file")
    tn.add_argument("--trees", type=int, default=100, help="trees in the forest")
    tn.add_argument("--threshold", type=float, default=LABEL_THRESHOLD_M,
                    help="label threshold on |measured - true range|, m (3x DW1000 LOS std)")
    tn.add_argument("--seed", type=int, default=0, help="forest random seed")
    tn.set_defaults(func=_cmd_train_nlos)


def _add_collisions(sub: argparse._SubParsersAction) -> None:
    """`uwbfuse collisions`: predict collisions among vehicles and with the map."""
    k = sub.add_parser(
        "collisions", help="predict collisions of vehicles with the map and each other",
        description="Predict each vehicle's footprint over [t, t + control_delay] (constant "
        "velocity and turn rate) and report warnings and collisions against the map "
        "([map], or a log's map_obstacles) and among the vehicles.",
    )
    k.add_argument("inputs", nargs="+", metavar="EST.tum",
                   help="one trajectory per vehicle (TUM), or logs with --method")
    k.add_argument("--config", metavar="FILE", help="[map] and [vehicle]")
    k.add_argument("--names", metavar="A,B,...", help="vehicle names (default: file stems)")
    k.add_argument("--out", default="collisions_out", metavar="DIR",
                   help="folder for events.csv, events.md and the map plot")
    k.add_argument("--method", help="estimate logs given as inputs first: " + METHOD_HELP)
    k.add_argument("--cov", metavar="C1.csv,...",
                   help="--cov-out CSV per trajectory, in order ('' for none)")
    k.add_argument("--scheduler", metavar="ADDRESS", help=SCHEDULER_HELP)
    k.add_argument("--workers", type=int, metavar="N", help=WORKERS_HELP)
    k.set_defaults(func=_cmd_collisions)


def _add_dump_config(sub: argparse._SubParsersAction) -> None:
    """`uwbfuse dump-config`: print the default configuration."""
    d = sub.add_parser("dump-config", help="print the default configuration (TOML, units)")
    d.set_defaults(func=_cmd_dump_config)


def build_parser() -> argparse.ArgumentParser:
    """The command line: the global options, then each subcommand's (`_add_<command>`);
    each subcommand's behaviour lives in its own module."""
    p = argparse.ArgumentParser(
        prog="uwbfuse",
        description="Factor-graph localisation from IMU, wheel odometry and UWB ranges.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("-v", "--verbose", action="store_true", help="log progress to stderr")
    p.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in (_add_simulate, _add_run, _add_eval, _add_compare, _add_montecarlo, _add_batch,
                _add_calibrate_nlos, _add_train_nlos, _add_collisions, _add_dump_config):
        add(sub)
    for sp in sub.choices.values():
        sp.formatter_class = _HelpFormatter
    return p


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread so it unwinds like Ctrl-C: temporary files are
    removed on the way out and the exit status is the conventional 128 + 15."""


def _on_sigterm(signum: int, frame: object) -> None:
    raise Terminated


def _handle_sigterm() -> Any:
    """Install the SIGTERM handler (main thread only); the previous handler, or None."""
    try:
        return signal.signal(signal.SIGTERM, _on_sigterm)
    except ValueError:  # not the main thread (e.g. main() called from a worker)
        return None


def _held_warnings(verbose: bool) -> logging.handlers.MemoryHandler | None:
    """Log to stderr; without --verbose the warnings are held until the command ends (a
    failed command prints only its error line)."""
    fmt = "%(levelname)s %(name)s: %(message)s"
    if verbose:
        logging.basicConfig(level=logging.INFO, format=fmt)
        return None
    out = logging.StreamHandler()
    out.setFormatter(logging.Formatter(fmt))
    held = logging.handlers.MemoryHandler(1 << 16, flushLevel=logging.CRITICAL + 1, target=out)
    logging.basicConfig(level=logging.WARNING, handlers=[held])
    logging.captureWarnings(True)  # numpy's RuntimeWarnings are held with the rest
    return held


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `uwbfuse` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    held = _held_warnings(args.verbose)
    if getattr(args, "method", None) is not None:
        from uwbfuse.estimator import Method

        try:
            Method(args.method)
        except ValueError:
            from uwbfuse.suggest import did_you_mean

            hint = did_you_mean(args.method, [m.value for m in Method])
            parser.error(f"unknown method {args.method!r}{hint} (one of: {METHOD_HELP})")
    previous = _handle_sigterm()
    try:
        return int(args.func(args))
    except UwbfuseError as e:
        if held is not None:
            held.buffer.clear()  # bad input: the one error line, not the warnings before it
        print(f"uwbfuse {args.command}: error: {e}", file=sys.stderr)
        return 2
    except Terminated:
        print(f"uwbfuse {args.command}: terminated", file=sys.stderr)
        return 128 + signal.SIGTERM
    except KeyboardInterrupt:
        print(f"uwbfuse {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # Output piped into a reader that closed early (`uwbfuse eval ... | head`): not an
        # error of ours; silence the flush at exit as the Python docs recommend.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        if held is not None:
            held.flush()


if __name__ == "__main__":
    sys.exit(main())
