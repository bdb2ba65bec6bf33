"""The `tecdard episodes` subcommands: `sync` (upload the recordings a directory holds), `query` (SQL over the
index), `fetch` (an episode back from the store) and `compact` (the index's files merged)."""
from __future__ import annotations

import argparse
import csv
import json
import pathlib
import sys

from tecdard.safejson import json_ready, show

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT = 0, 1, 2


def _say(verb: str, text: str) -> None:
    print(f"tecdard episodes {verb}: {text}", file=sys.stderr, flush=True)


def _store_and_dir(args):
    """(StoreParams, recordings directory) from --config's `store` and `record` sections, then --store
    and the other options over them; ConfigError or StoreError otherwise."""
    from tecdard.config import Config, ConfigError
    from tecdard.fleet.episodes import StoreParams, StoreError, url_problem
    params, directory = StoreParams(), None
    if args.config:
        cfg = Config.load(args.config)
        params = StoreParams.from_config(cfg.section("store"))
        from tecdard.runtime.recorder import RecordParams
        directory = RecordParams.from_config(cfg.section("record")).dir
    changes = {k: v for k, v in (("url", args.store), ("endpoint", args.endpoint), ("region", args.region)) if v}
    if args.allow_http:
        changes["allow_http"] = True
    params = StoreParams(**{**params.__dict__, **changes})
    if not params.url:
        raise ConfigError("no store: --store file:///DIR or s3://BUCKET/PREFIX (or --config with store.url)")
    problem = url_problem(params.url)
    if problem:
        raise StoreError(f"--store {problem}")
    return params, directory


def _sync(args) -> int:
    from tecdard.config import ConfigError
    from tecdard.fleet.episodes import EpisodeStore, StoreError, is_uploaded, upload
    from tecdard.recording.format import RecordingError
    try:
        params, directory = _store_and_dir(args)
        store = EpisodeStore(params)
    except (ConfigError, StoreError) as exc:
        _say("sync", str(exc))
        return EXIT_BAD_INPUT
    folder = pathlib.Path(args.dir or directory or "")
    if not args.dir and not directory:
        _say("sync", "which recordings? --dir DIR (or --config with record.dir)")
        return EXIT_BAD_INPUT
    if not folder.is_dir():
        _say("sync", f"--dir {show(str(folder))}: no such directory")
        return EXIT_BAD_INPUT
    files = sorted(f for f in folder.glob("*.npz") if args.again or not is_uploaded(f, store.url))
    done = failed = 0
    for f in files:
        try:
            ep = upload(store, f, robot=args.robot, mcap=not args.no_mcap, config=args.config)
        except KeyboardInterrupt:
            _say("sync", f"interrupted: {done} uploaded, {len(files) - done - failed} left (run again to go on)")
            return 130
        except (StoreError, RecordingError, OSError) as exc:
            failed += 1
            _say("sync", f"{f.name}: {exc}")
            continue
        done += 1
        print(f"{f.name} -> {store.url}/{ep.key('.npz')}" + (f" ({len(ep.contacts)} contacts)" if ep.contacts else ""))
    _say("sync", f"{done} uploaded, {failed} failed, {len(list(folder.glob('*.npz'))) - len(files)} there already")
    return EXIT_OK if not failed else EXIT_FAILED


def _index(args):
    from tecdard.fleet.episodes import EpisodeStore
    from tecdard.fleet.index import Index
    params, _ = _store_and_dir(args)
    return Index(EpisodeStore(params, create=False), pathlib.Path(args.cache) if args.cache else None)


def _query(args) -> int:
    from tecdard.config import ConfigError
    from tecdard.fleet.episodes import StoreError
    from tecdard.fleet.index import QueryError, query, table_text
    try:
        index = _index(args)
        columns, rows = query(index, args.sql)
    except (ConfigError, StoreError, QueryError) as exc:
        _say("query", str(exc))
        return EXIT_BAD_INPUT
    for name, why in index.skipped:
        _say("query", f"index file {show(name)} left out: {why}")
    if args.json:
        print(json.dumps([json_ready(dict(zip(columns, (_plain(v) for v in r)))) for r in rows]))
    elif args.csv:
        out = csv.writer(sys.stdout)
        out.writerow(columns)
        out.writerows([[_plain(v) for v in r] for r in rows])
    elif columns:
        print(table_text(columns, rows))
    return EXIT_OK


def _plain(v):
    """A DuckDB value as JSON or CSV takes it (times as ISO 8601)."""
    if hasattr(v, "isoformat"):
        return v.isoformat()
    return v


def _fetch(args) -> int:
    from tecdard.config import ConfigError
    from tecdard.fleet.episodes import StoreError
    from tecdard.fleet.index import QueryError
    try:
        index = _index(args)
        con = index.connect()
        try:
            rows = con.execute("SELECT id, npz_key, mcap_key FROM episodes WHERE id = ? OR episode = ? ORDER BY id",
                               [args.id, args.id]).fetchall()
        finally:
            con.close()
        if not rows:
            raise QueryError(f"{show(args.id)}: no such episode in the index (`tecdard episodes query "
                             "\"SELECT id FROM episodes\"`)")
        if len(rows) > 1:
            raise QueryError(f"{show(args.id)} names {len(rows)} episodes ({', '.join(r[0] for r in rows[:4])}): "
                             "give its robot/name id")
        ep_id, npz_key, mcap_key = rows[0]
        out = pathlib.Path(args.output)
        out.mkdir(parents=True, exist_ok=True)
        got = []
        for key in (npz_key, mcap_key if args.mcap else None):
            if not key:
                continue
            dest = out / pathlib.PurePosixPath(key).name
            if dest.exists():
                raise QueryError(f"{dest}: already there; not overwritten (-o another directory)")
            data = index.store.get(key)
            tmp = dest.with_name(dest.name + ".part")
            tmp.write_bytes(data)
            tmp.replace(dest)
            got.append(dest)
    except (ConfigError, StoreError, QueryError, OSError) as exc:
        _say("fetch", str(exc))
        return EXIT_BAD_INPUT
    for dest in got:
        print(dest)
    _say("fetch", f"{ep_id}: `tecdard localize {got[0]}`, `tecdard plot`, `tecdard export`")
    return EXIT_OK


def _compact(args) -> int:
    from tecdard.config import ConfigError
    from tecdard.fleet.episodes import EpisodeStore, StoreError
    from tecdard.fleet.index import compact
    try:
        params, _ = _store_and_dir(args)
        merged = compact(EpisodeStore(params, create=False), pathlib.Path(args.cache) if args.cache else None)
    except (ConfigError, StoreError) as exc:
        _say("compact", str(exc))
        return EXIT_BAD_INPUT
    _say("compact", ", ".join(f"{table}: {n} files merged" for table, n in merged.items()))
    return EXIT_OK


def _store_options(p) -> None:
    p.add_argument("--store", help="the store: file:///DIR (local) or s3://BUCKET/PREFIX (S3: AWS, MinIO, Ceph; "
                                   "credentials from AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY)")
    p.add_argument("--endpoint", help="an S3-compatible service's URL (MinIO, Ceph); default AWS")
    p.add_argument("--region", help="the S3 region")
    p.add_argument("--allow-http", action="store_true", help="plain HTTP to the endpoint (a lab's MinIO without TLS)")
    p.add_argument("--config", help="a daemon's config: its `store` (and `record.dir`) sections; the options above "
                                    "override them")


def add_parser(sub) -> None:
    eps = sub.add_parser("episodes",
                         help="the fleet's contact episodes in one store: sync, query (SQL), fetch, compact",
                         description="Recordings in object storage (file:// or s3://) with a Parquet index queried "
                                     "by DuckDB (docs/fleet.md).")
    verbs = eps.add_subparsers(dest="episodes_cmd", required=True)
    p = verbs.add_parser("sync", help="upload the recordings of a directory not uploaded yet (each at most once)")
    _store_options(p)
    p.add_argument("--dir", help="the recordings (default: --config's record.dir)")
    p.add_argument("--robot", help="the robot of recordings that do not name one (simulated ones)")
    p.add_argument("--no-mcap", action="store_true", help="no MCAP beside each recording")
    p.add_argument("--again", action="store_true", help="also those marked uploaded to this store: still never twice")
    p.set_defaults(func=_sync)
    p = verbs.add_parser("query", help="SQL (DuckDB) over the index: views `episodes` and `contacts`",
                         description="Views: episodes (one row per episode: id, robot, episode, start_time, day, task, "
                                     "verb, reason, backend, model, estimator, config_digest, eta, grip_force_n, "
                                     "duration_s (s), result, contacts, npz_key, mcap_key, bytes, uploaded_at, "
                                     "version) "
                                     "and contacts (one per contact: id, robot, episode, n, onset_t (s), onset_time, "
                                     "detect_latency_s, x_m, y_m, z_m (world, m), sigma_m (one-sigma, m), std_x_m, "
                                     "std_y_m, std_z_m, converged_after_s (s), error_m (m, against a truth)).",
                         epilog='example: tecdard episodes query --store file:///srv/tecdar/episodes '
                                '"SELECT robot, count(*) FROM episodes GROUP BY robot"')
    p.add_argument("sql", help="the query")
    _store_options(p)
    p.add_argument("--cache", help="where an S3 store's index files are kept between queries (default: a temporary "
                                   "directory)")
    fmt = p.add_mutually_exclusive_group()
    fmt.add_argument("--json", action="store_true", help="rows as a JSON list of objects")
    fmt.add_argument("--csv", action="store_true", help="rows as CSV")
    p.set_defaults(func=_query)
    p = verbs.add_parser("fetch", help="bring an episode back from the store (to localize, plot or export)")
    p.add_argument("id", help="the episode's id (robot/name) or its name")
    _store_options(p)
    p.add_argument("-o", "--output", default=".", help="the directory it goes to (default .); nothing is overwritten")
    p.add_argument("--mcap", action="store_true", help="its MCAP too")
    p.add_argument("--cache", help=argparse.SUPPRESS)
    p.set_defaults(func=_fetch)
    p = verbs.add_parser("compact", help="merge the index's per-episode files into one part")
    _store_options(p)
    p.add_argument("--cache", help=argparse.SUPPRESS)
    p.set_defaults(func=_compact)
