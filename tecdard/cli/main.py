"""The `tecdard` command line: `run` the daemon, `demo` the whole pipeline on the simulated robot."""
from __future__ import annotations

import argparse
import functools
import json
import logging
import os
import pathlib
import re
import sys

from tecdard.config import Config, ConfigError
from tecdard.safejson import show


def announce_compile() -> None:
    """One log line before a start that must compile the estimator's kernels (tecdard.kernel_cache)."""
    from tecdard.tools import kernel_cache
    try:
        cache = kernel_cache.state()
    except Exception as exc:         # the check must never stop a start
        logging.getLogger("tecdar").debug("kernel cache check failed: %s", exc)
        return
    if not cache.warm:
        logging.getLogger("tecdar").warning("%s", cache.describe())


def _cmd_warm(args) -> int:
    from tecdard.tools import kernel_cache
    before = kernel_cache.state()
    if not before.warm:
        print(f"compiling the estimator's kernels into {before.path} (about {kernel_cache.COLD_COMPILE_S:.0f} s "
              "on 2 cores) ...", flush=True)
    after, took = kernel_cache.warm()
    # an uncachable install still runs (each start compiles): said, not an install failure
    print(f"{after.describe()}; {'loaded' if before.warm else 'compiled'} in {took:.1f} s")
    return 0


def _cmd_run(args) -> int:
    # maps, recordings and logs the daemon writes are the operator's alone (0600/0700), as the
    # unit's UMask=0077 has it, whoever starts the daemon
    os.umask(0o077)
    try:
        cfg = Config.load(args.config)
        announce_compile()
        from tecdard.runtime.daemon import Daemon   # heavy imports only once the config file exists
        daemon = Daemon(cfg, listen=[args.listen] if args.listen else None)
    except ConfigError as exc:
        print(f"tecdard: config error: {exc}", file=sys.stderr)
        return 2
    from tecdard.robots.backends import BackendError
    try:
        return daemon.run()
    except BackendError as exc:
        print(f"tecdard: {exc}", file=sys.stderr)
        return 1
    except Exception as exc:        # zenoh.ZError: cannot listen (address in use, no such interface)
        if type(exc).__module__.split(".")[0] != "zenoh":
            raise
        print(f"tecdard: Zenoh: {str(exc).splitlines()[0][:300]}", file=sys.stderr)
        return 1


MAX_RATE_HZ = 100_000.0      # localize's --rate: more rows per second than any IMU delivers is a typo


def _refused(command: str, msg: str) -> int:
    """A command's bad input: one line on stderr naming the command, and exit status 2."""
    print(f"tecdard {command}: {msg}", file=sys.stderr)
    return 2


class _BadInput(Exception):
    """A command-line tool's input that cannot be used; the message is one line (exit 2)."""


def _recording_and_pipeline(args):
    """The recording named by args.recording, its live_* log (None for any other, or with
    --ignore-live) and a contact pipeline from args.config's `estimator` section; _BadInput otherwise."""
    from tecdard.control.geometry import quat_to_matrix
    from tecdard.control import estimators
    from tecdard.control.pipeline import ContactPipeline
    from tecdard.recording.format import RecordingError, load_live, load_recording

    method = getattr(args, "method", None)
    if method is not None and method not in estimators.names():
        raise _BadInput(f"--method: unknown estimator {show(method)} (known: {', '.join(estimators.names())})")
    try:
        rec = load_recording(args.recording)
        live = None if getattr(args, "ignore_live", False) else load_live(args.recording, rec)
    except RecordingError as exc:
        raise _BadInput(str(exc)) from None
    no_plane = getattr(args, "no_plane", False)
    try:
        cfg = Config.load(args.config) if args.config else Config({})
        section = cfg.section("estimator")
        pipeline = ContactPipeline.from_config(section, quat_to_matrix(rec.imu_in_tcp_quat), rec.imu_rate_hz,
                                  method=method, plane_normal=None if no_plane else rec.plane_normal)
        if no_plane:
            pipeline.params.plane_normal = None
        unused = section.unused_keys()
        if unused:
            raise ConfigError(f"{unused[0]}: unknown option")
    except ConfigError as exc:
        raise _BadInput(f"config error: {exc}") from None
    return rec, live, pipeline


def _estimates(args, rec, live, pipeline, rate_hz: float = 1000.0, on_estimate=None, on_event=None):
    """(rows, onset_t, last) of the replay: as fed live for a daemon recording, else causally in chunks."""
    from tecdard.tools import localize as L
    try:
        if live is not None:
            return L.replay_live(rec, live, pipeline, on_estimate)
        return L.replay(rec, pipeline, rate_hz, on_estimate=on_estimate, on_event=on_event)
    except Exception as exc:        # a recording the checks let through but the estimator cannot take
        logging.getLogger("tecdar").debug("replay failed", exc_info=True)
        raise _BadInput(f"{show(args.recording, 200)}: could not be replayed ({type(exc).__name__}: "
                        f"{str(exc).splitlines()[0][:200] if str(exc) else ''}); please report it with the file") from None


def _cmd_localize(args) -> int:
    from tecdard.tools import localize as L

    bad = functools.partial(_refused, "localize")

    if not 0 < args.rate <= MAX_RATE_HZ:
        return bad(f"--rate: must be in (0, {MAX_RATE_HZ:g}] rows per second, got {args.rate:g}")
    out = None
    if args.out:
        try:
            out = open(args.out, "w")             # before the replay: a bad path fails at once
        except OSError as exc:
            return bad(f"--out: cannot write {show(args.out, 200)} ({exc.strerror or type(exc).__name__})")
    try:
        rec, live, pipeline = _recording_and_pipeline(args)
        rows, onset_t, last = _estimates(args, rec, live, pipeline, args.rate)
    except _BadInput as exc:
        return bad(str(exc))
    if out is not None:
        try:
            with out:
                L.write_csv(out, rows)
        except OSError as exc:
            return bad(f"--out: writing {show(args.out, 200)} failed ({exc.strerror or type(exc).__name__})")
    if onset_t is None or last is None:
        if args.json:
            print(json.dumps({"onset_t": None, "p_c": None, "std": None, "method": pipeline.method}))
        print("tecdard localize: no contact detected", file=sys.stderr)
        return L.EXIT_NO_CONTACT
    L.print_summary(L.summary(onset_t, last), args.json)
    return L.EXIT_OK


def _cmd_export(args) -> int:
    from tecdard.tools import export
    from tecdard.recording.format import load_truth

    bad = functools.partial(_refused, "export")

    estimates, events = [], []
    try:
        rec, live, pipeline = _recording_and_pipeline(args)
        _estimates(args, rec, live, pipeline, on_estimate=estimates.append, on_event=events.append)
        if live is not None:
            events = live.events          # the pipeline's and the daemon's, as they happened live
        try:
            truth = load_truth(args.recording)
        except Exception:
            truth = {}
        n = export.write_mcap(args.mcap, rec, estimates, events, truth)
    except _BadInput as exc:
        return bad(str(exc))
    except export.ExportError as exc:
        return bad(str(exc))
    print(f"{args.mcap}: {n} messages ({len(estimates)} estimates, {len(events)} events)")
    return 0


def _cmd_calibrate_eta(args) -> int:
    import argparse as ap

    import numpy as np

    from tecdard.tools import calibrate as K

    bad = functools.partial(_refused, "calibrate-eta")

    if (args.contact is None) == (args.radius is None):
        return bad("give the contact's position (--contact x,y,z, world, m) or the lever arm (--radius r, m)")
    contact = None
    if args.contact is not None:
        try:
            contact = np.array([float(x) for x in args.contact.split(",")])
        except ValueError:
            contact = None
        if contact is None or contact.shape != (3,) or not np.all(np.isfinite(contact)):
            return bad(f"--contact: expected three numbers x,y,z in metres, got {show(args.contact)}")
    if args.radius is not None and not (np.isfinite(args.radius) and 0.001 <= args.radius <= 2.0):
        return bad(f"--radius: expected 0.001..2 m, got {args.radius!r}")
    if len(args.recordings) < K.MIN_RECORDINGS:
        return bad(f"needs at least {K.MIN_RECORDINGS} recordings (got {len(args.recordings)}): eta's uncertainty "
                   "comes from more than one probe")
    rows, lag_curves = [], []
    try:
        for path in args.recordings:
            one = ap.Namespace(recording=path, config=args.config, method=None, ignore_live=False, no_plane=False)
            rec, live, pipeline = _recording_and_pipeline(one)
            _, onset_t, _ = _estimates(one, rec, live, pipeline)
            name = pathlib.Path(path).name
            if onset_t is None:
                raise K.CalibrationError(f"{name}: no contact onset detected")
            force = K.grip_force_of(name, rec)
            eta, se, n = K.eta_of(name, rec, onset_t, contact, args.radius)
            rows.append((force, eta, se))
            if contact is not None:
                lags, rss = K.lag_residuals(rec, onset_t, contact)
                lag_curves.append(rss)
            print(f"{name}: grip {force:g} N, eta {eta:.3f} +- {se:.3f} ({n} windows)")
    except _BadInput as exc:
        return bad(str(exc))
    except K.CalibrationError as exc:
        return bad(str(exc))
    pooled = K.pool(rows)
    print("grip force N | eta | one-sigma | recordings")
    for force, eta, sigma, n in pooled:
        print(f"{force:12g} | {eta:.3f} | {sigma:.3f} | {n}")
    print(K.table_yaml(pooled))
    if lag_curves:
        try:
            print(f"estimator.fingertip_lag_s: {K.best_lag(lag_curves, lags):.4f}")
        except K.LagAtBound as exc:            # eta stands; the lag is not found
            return bad(str(exc))
    return 0


def _cmd_plot(args) -> int:
    import numpy as np

    from tecdard.tools import plot
    from tecdard.recording.format import load_truth

    bad = functools.partial(_refused, "plot")

    try:
        rec, live, pipeline = _recording_and_pipeline(args)
        rows, onset_t, _ = _estimates(args, rec, live, pipeline)
        try:
            truth = load_truth(args.recording)     # optional: a truth that cannot be read is left out
        except Exception:
            truth = {}
        if np.shape(truth.get("p_c")) != (3,) or not np.all(np.isfinite(truth.get("p_c", np.nan))):
            truth.pop("p_c", None)
        plot.draw(rec, rows, onset_t, truth, args.out, f"{pathlib.Path(args.recording).name}, {pipeline.method}")
    except _BadInput as exc:
        return bad(str(exc))
    except plot.PlotError as exc:
        return bad(str(exc))
    print(f"{args.out}: {len(rows)} estimates" + ("" if onset_t is not None else ", no contact detected"))
    return 0


def _cmd_sim_record(args) -> int:
    """sim-record: sim/scenarios.py's signal model, or (--engine mujoco) the cutter or the pen in
    MuJoCo's physics (sim/mujoco_source.py), from the options the engine's scenario has."""
    import dataclasses

    from tecdard.recording.format import Recording, save_recording
    if args.engine == "mujoco":
        try:
            import mujoco  # noqa: F401

            from tecdard.sim.mujoco_source import MujocoScenario as Scenario, generate
        except ImportError:
            print("tecdard sim-record: --engine mujoco needs mujoco: pip install 'tecdar[bench]'", file=sys.stderr)
            return 2
    else:
        from tecdard.sim.scenarios import Scenario, generate
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(Scenario)
              if f.name != "extra" and getattr(args, f.name, None) is not None}
    try:
        sc = Scenario(**values)
        fields, truth = generate(sc)
    except ValueError as exc:
        print(f"tecdard sim-record: {exc}", file=sys.stderr)
        return 2
    rec = Recording.from_fields(fields)
    save_recording(args.out, rec, truth)
    what = f"mujoco {sc.motion}" if args.engine == "mujoco" else sc.kind
    print(f"wrote {args.out}: {what}, {len(rec.imu_t)} IMU samples at {sc.imu_hz:g} Hz, "
          f"{len(rec.tcp_t)} TCP samples at {sc.tcp_hz:g} Hz, onset at {float(truth['onset_t']):.4f} s")
    return 0


def _scenario_options(p) -> None:
    """One option per Scenario field, typed from its default."""
    import dataclasses

    from tecdard.sim.scenarios import KINDS, Scenario

    def vec(text: str):
        try:
            return tuple(float(x) for x in text.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None

    def flag(text: str) -> bool:
        if text.lower() in ("1", "true", "yes", "on"):
            return True
        if text.lower() in ("0", "false", "no", "off"):
            return False
        raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}")

    for f in dataclasses.fields(Scenario):
        if f.name == "extra":
            continue
        opt = "--" + f.name.replace("_", "-")
        default = f.default
        if f.name == "kind":
            p.add_argument(opt, choices=KINDS, default=None, help=f"scenario (default {default})")
        elif isinstance(default, bool) or f.name == "tcp_rotates":
            p.add_argument(opt, type=flag, default=None, metavar="BOOL", help=f"default {default}")
        elif isinstance(default, int) and not isinstance(default, bool):
            p.add_argument(opt, type=int, default=None, help=f"default {default}")
        elif isinstance(default, tuple):
            p.add_argument(opt, type=vec, default=None, metavar="X,Y,Z", help=f"default {','.join(map(str, default))}")
        else:
            p.add_argument(opt, type=float, default=None, help=f"default {default}")


def _cmd_imu(args) -> int:
    """Read the fingertip board for a while; print rates, counters and the latest sample in SI."""
    import time

    from tecdard.drivers.serial_imu import PortError, SerialImuSource, SerialParams

    vid = pid = None
    if args.vid_pid:
        try:
            vid, pid = (int(x, 16) for x in args.vid_pid.split(":"))
        except ValueError:
            print(f"tecdard imu: --vid-pid: expected hex VID:PID such as 0483:5740, got {args.vid_pid!r}",
                  file=sys.stderr)
            return 2
    if not args.port and vid is None:
        print("tecdard imu: give --port PATH or --vid-pid VID:PID", file=sys.stderr)
        return 2
    src = SerialImuSource(SerialParams(port=args.port, vid=vid, pid=pid, serial_number=args.serial_number))
    try:
        src.open()
    except PortError as exc:
        print(f"tecdard imu: {exc}", file=sys.stderr)
        return 1
    t_start = time.monotonic()
    n_samples = 0
    while time.monotonic() - t_start < args.seconds:
        out = src.read(0.05)
        if out is not None:
            n_samples += len(out[0])
    elapsed = time.monotonic() - t_start
    src.close()
    c = src.counters()
    report = {
        "port": src.port_path, "seconds": round(elapsed, 3),
        "sample_rate_hz": round(n_samples / elapsed, 1),
        "byte_rate_bps": round(c["bytes_in"] / elapsed, 1),
        "packet_rate_hz": round(c["good_packets"] / elapsed, 1),
        "status": None if src.status is None else {"odr_hz": src.status.odr_hz, "gyro_fs_dps": src.status.gyro_fs_dps,
                                                   "accel_fs_g": src.status.accel_fs_g, "flags": src.status.flags},
        "counters": c,
        "latest": None if src.latest is None else {"t": src.latest[0], "gyro_rad_s": src.latest[1].tolist(),
                                                   "accel_m_s2": src.latest[2].tolist()},
    }
    if args.json:
        print(json.dumps(report))
    else:
        st = report["status"]
        print(f"{src.port_path}: {report['sample_rate_hz']:.0f} samples/s, {report['packet_rate_hz']:.0f} packets/s, "
              f"{report['byte_rate_bps'] / 1000:.1f} kB/s over {elapsed:.1f} s")
        print("status: " + ("none received (using config full scales)" if st is None else
                            f"ODR {st['odr_hz']} Hz, gyro {st['gyro_fs_dps']} dps, accel {st['accel_fs_g']} g, flags {st['flags']:#x}"))
        print("counters: " + ", ".join(f"{k} {v}" for k, v in c.items()))
        if report["latest"]:
            g, a = report["latest"]["gyro_rad_s"], report["latest"]["accel_m_s2"]
            print(f"latest: gyro [{', '.join(f'{x:+.4f}' for x in g)}] rad/s, accel [{', '.join(f'{x:+.3f}' for x in a)}] m/s^2")
        else:
            print("latest: no samples received")
    return 0 if n_samples else 1


def _cmd_demo(args) -> int:
    from tecdard.tools.demo import run_demo
    return run_demo(args.config, args.angle)


_NEGATIVE_VALUE = re.compile(r"^-(\d|\.\d)")


def join_negative_values(argv: list[str]) -> list[str]:
    """`--direction -0.26,0,0.96` as `--direction=-0.26,0,0.96`: argparse takes a value that starts
    with '-' and is not one plain number for an option, and the vector arguments are lists."""
    out: list[str] = []
    for arg in argv:
        if (out and out[-1].startswith("--") and "=" not in out[-1] and out[-1] != "--"
                and _NEGATIVE_VALUE.match(arg)):
            out[-1] = f"{out[-1]}={arg}"
        else:
            out.append(arg)
    return out


def main(argv: list[str] | None = None) -> int:
    argv = join_negative_values(sys.argv[1:] if argv is None else list(argv))
    parser = argparse.ArgumentParser(prog="tecdard", description="Transient extrinsic contact detection and ranging daemon")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("run", help="run the daemon")
    p.add_argument("--config", required=True, help="YAML configuration file")
    p.add_argument("--listen", help="Zenoh endpoint to listen on, overrides zenoh.listen (e.g. tcp/127.0.0.1:7507)")
    p.set_defaults(func=_cmd_run)
    p = sub.add_parser("localize", help="estimate the contact in a recording (tecdar-recording/1)")
    p.add_argument("recording", help="REC.npz")
    p.add_argument("--out", help="write estimates as CSV: t,px,py,pz,sx,sy,sz")
    p.add_argument("--method", help="estimator (default: the config's, else ekf); an unknown name lists them all")
    p.add_argument("--rate", type=float, default=1000.0, help="at most this many rows per second (default 1000)")
    p.add_argument("--json", action="store_true", help="print the summary as a JSON object")
    p.add_argument("--config", help="YAML whose `estimator` section tunes the pipeline")
    p.add_argument("--no-plane", action="store_true", help="ignore plane_normal: use the 3D estimator")
    p.add_argument("--ignore-live", action="store_true",
                   help="a daemon recording: replay it as any recording, not as its live estimator was fed")
    p.set_defaults(func=_cmd_localize)
    p = sub.add_parser("plot", help="draw a recording: IMU and onset, the estimate with its 3-sigma band, its error")
    p.add_argument("recording", help="REC.npz")
    p.add_argument("-o", "--out", required=True, help="image to write (png, pdf, svg)")
    p.add_argument("--method", help="estimator (default: the config's, else ekf)")
    p.add_argument("--config", help="YAML whose `estimator` section tunes the pipeline")
    p.add_argument("--ignore-live", action="store_true", help="a daemon recording: replay it as any recording")
    p.set_defaults(func=_cmd_plot)
    p = sub.add_parser("export", help="write a recording and its replayed estimate as MCAP for Foxglove")
    p.add_argument("recording", help="REC.npz")
    p.add_argument("--mcap", required=True, help="OUT.mcap (replaced if it exists)")
    p.add_argument("--method", help="estimator (default: the config's, else ekf)")
    p.add_argument("--config", help="YAML whose `estimator` section tunes the pipeline")
    p.add_argument("--ignore-live", action="store_true", help="a daemon recording: replay it as any recording")
    p.set_defaults(func=_cmd_export)
    p = sub.add_parser("calibrate-eta", help="eta per grip force from probes against a contact at a known place")
    p.add_argument("recordings", nargs="+", help="REC.npz ... (each with a grip_force key or meta.grip_force)")
    p.add_argument("--contact", help="the contact's position x,y,z (world, m)")
    p.add_argument("--radius", type=float, help="or the lever arm from the TCP to the contact (m)")
    p.add_argument("--config", help="YAML whose `estimator` section finds the onsets")
    p.set_defaults(func=_cmd_calibrate_eta)
    p = sub.add_parser("sim-record", help="write a simulated scenario as a recording with truth_* keys")
    p.add_argument("out", help="OUT.npz")
    p.add_argument("--engine", choices=("scenarios", "mujoco"), default="scenarios",
                   help="scenarios: sim/scenarios.py's signal model (default); mujoco: rigid-body physics of the "
                        "paper cutter, a pen on its tip or a block on a table edge (sim/mujoco_source.py, the bench extra)")
    p.add_argument("--motion", choices=("arc", "arc-turning", "push", "slip", "circle", "tilt", "ongoing"),
                   help="with --engine mujoco: the TCP's path (default arc); slip: the arc, the grasp slipping "
                        "on the handle; circle: the pen on its tip; tilt: a block tipped on its edge; ongoing: "
                        "the block slid into the edge at speed, then tipped")
    _scenario_options(p)
    p.set_defaults(func=_cmd_sim_record)
    p = sub.add_parser("imu", help="read the fingertip IMU board: rates, counters, latest sample")
    p.add_argument("--port", help="serial device path (e.g. /dev/ttyACM0)")
    p.add_argument("--vid-pid", help="find the board by USB VID:PID (hex), e.g. 0483:5740")
    p.add_argument("--serial-number", help="with --vid-pid: the board's USB serial number")
    p.add_argument("--seconds", type=float, default=2.0, help="how long to read (default 2)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=_cmd_imu)
    from tecdard.cli.task_verbs import add_parsers
    add_parsers(sub)
    p = sub.add_parser("doctor", help="check whether this host is ready to run the daemon beside a real arm")
    p.add_argument("--config", default="/etc/tecdar/tecdard.yaml", help="the daemon's config (default: the unit's)")
    p.set_defaults(func=lambda a: __import__("tecdard.tools.doctor", fromlist=["main"]).main(a.config))
    p = sub.add_parser("warm", help="compile the estimator's kernels into numba's cache (make install does)")
    p.set_defaults(func=_cmd_warm)
    p = sub.add_parser("demo", help="start the daemon on the simulated robot and rotate the paper cutter")
    p.add_argument("--config", default="configs/sim.yaml")
    p.add_argument("--angle", type=float, default=30.0, help="rotation, degrees")
    p.set_defaults(func=_cmd_demo)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    return args.func(args)
