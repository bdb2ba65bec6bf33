"""`tecdard export REC.npz --mcap OUT.mcap`: a recording, with the estimate replayed over it, as an MCAP
file for Foxglove (the writing is tecdard.recording.mcap's). `tecdard export --lerobot DIR REC.npz ...` (or
`--store URL --query SQL`): daemon recordings as a LeRobot v3 dataset (tecdard.recording.lerobot's)."""
from __future__ import annotations

import pathlib
import tempfile
import time

from tecdard.tools.args import BadInput, checked_method, refused, show_path_error


def add_parser(sub) -> None:
    p = sub.add_parser("export", help="write a recording and its replayed estimate as MCAP for Foxglove, or daemon "
                                      "recordings as a LeRobot v3 dataset (50 fps, the control tick)")
    p.add_argument("recordings", nargs="*", metavar="REC.npz", help="the recording (--mcap: one; --lerobot: any)")
    out = p.add_mutually_exclusive_group(required=True)
    out.add_argument("--mcap", help="OUT.mcap (replaced if it exists)")
    out.add_argument("--lerobot", metavar="DIR", help="a new LeRobot v3 dataset in DIR (absent or empty): one "
                                                      "episode per daemon recording")
    p.add_argument("--store", help="--lerobot: the episode store (file:///DIR or s3://BUCKET/PREFIX) whose "
                                   "--query picks the recordings")
    p.add_argument("--query", metavar="SQL", help="--lerobot with --store: SQL over the episode index "
                                                  "(`tecdard episodes query`) returning an npz_key column")
    p.add_argument("--method", help="--mcap: estimator (default: the config's, else ekf)")
    p.add_argument("--config", help="YAML whose `estimator` section tunes the pipeline (--mcap)")
    p.add_argument("--ignore-live", action="store_true",
                   help="--mcap, a daemon recording: replay it as any recording, not as its live estimator was fed")
    p.set_defaults(func=main)


def main(args) -> int:
    """`tecdard export`: exit 0, or 2 with one line."""
    return _lerobot(args) if args.lerobot else _mcap(args)


def _mcap(args) -> int:
    from tecdard.files import OutputError, check_output, replacing
    from tecdard.recording.format import RecordingError
    from tecdard.recording.mcap import ExportError, export_mcap
    from tecdard.recording.replay import ReplayError

    try:
        if len(args.recordings) != 1 or args.store or args.query:
            raise BadInput(f"--mcap: one recording, got {len(args.recordings)}" if len(args.recordings) != 1 else
                           "--store and --query go with --lerobot")
        (recording,) = args.recordings
        method = checked_method(args)
        check_output(args.mcap, "--mcap", [recording])       # never over the input, and before the replay
        with replacing(args.mcap, "--mcap") as tmp:     # a failed write leaves what was there
            n, found, events = export_mcap(recording, tmp, args.config, method, args.ignore_live)
    except (BadInput, ExportError, RecordingError, ReplayError) as exc:
        return refused("export", str(exc))
    except OutputError as exc:
        return refused("export", show_path_error(exc))
    print(f"{args.mcap}: {n} messages ({len(found)} estimates, {len(events)} events)")
    return 0


def _lerobot(args) -> int:
    from tecdard.recording.lerobot import DatasetError, episode_of, write_dataset

    out = pathlib.Path(args.lerobot)
    try:
        if args.method or args.config or args.ignore_live:
            raise BadInput("--method, --config and --ignore-live go with --mcap (a dataset holds the live estimates)")
        if bool(args.store) != bool(args.query):
            raise BadInput("--store and --query go together")
        if args.store and args.recordings:
            raise BadInput("recordings or --store with --query, not both")
        if out.exists() and (not out.is_dir() or any(out.iterdir())):
            raise BadInput(f"--lerobot: {out} is there and not an empty directory (a dataset is written whole)")
        started = time.monotonic()
        with tempfile.TemporaryDirectory() as fetched:
            paths = _from_store(args, pathlib.Path(fetched)) if args.store else list(args.recordings)
            if not paths:
                raise BadInput("no recordings: name them, or --store with a --query that returns some")
            episodes = [episode_of(p) for p in paths]
            out.mkdir(parents=True, exist_ok=True)
            info = write_dataset(out, episodes, episodes[0].meta.get("robot"))
    except (BadInput, DatasetError) as exc:
        return refused("export", str(exc))
    except OSError as exc:
        return refused("export", f"--lerobot: {exc.strerror or exc} ({out})")
    except KeyboardInterrupt:
        refused("export", f"interrupted: {out} is not a complete dataset")
        return 130
    seconds = info["total_frames"] / info["fps"]
    print(f"{out}: {info['total_episodes']} episodes, {info['total_frames']} frames ({seconds:.1f} s at "
          f"{info['fps']} fps), {len(set(e.task for e in episodes))} tasks, in {time.monotonic() - started:.2f} s")
    return 0


def _from_store(args, into: pathlib.Path) -> list[pathlib.Path]:
    """The recordings --query picks from --store, fetched into `into`."""
    from tecdard.config import ConfigError
    from tecdard.fleet.episodes import EpisodeStore, StoreError, StoreParams, url_problem
    from tecdard.fleet.index import Index, QueryError, query

    problem = url_problem(args.store)
    if problem:
        raise BadInput(f"--store {problem}")
    try:
        store = EpisodeStore(StoreParams(url=args.store), create=False)
        columns, rows = query(Index(store, None), args.query)
        if "npz_key" not in columns:
            raise BadInput(f"--query: its columns ({', '.join(columns) or 'none'}) have no npz_key, the recordings' "
                           "keys (select npz_key from episodes where ...)")
        paths = []
        for row in rows:
            key = row[columns.index("npz_key")]
            path = into / f"{len(paths):05d}-{pathlib.PurePosixPath(str(key)).name}"
            path.write_bytes(store.get(str(key)))
            paths.append(path)
        return paths
    except (ConfigError, StoreError, QueryError) as exc:
        raise BadInput(f"--store: {exc}") from None
