"""The episode index read and kept: DuckDB views `episodes` and `contacts` over the store's Parquet files (read in
place from a file:// store, fetched into a local cache from S3), one row per episode and per contact however
often a file was retried or compacted; and compaction, which merges the per-episode files into one part."""
from __future__ import annotations

import datetime
import logging
import pathlib
import tempfile
import uuid

from tecdard.fleet.episodes import (CONTACT_COLUMNS, CONTACTS_TABLE, EPISODE_COLUMNS, EPISODES_TABLE, INDEX,
                                    LATER_COLUMNS, MAX_INDEX_FILE_BYTES, EpisodeStore, StoreError)
from tecdard.safejson import first_line

log = logging.getLogger("tecdar.episodes")

TABLES = {EPISODES_TABLE: (EPISODE_COLUMNS, ("id",)), CONTACTS_TABLE: (CONTACT_COLUMNS, ("id", "n"))}
MAX_ROWS_SHOWN = 10000          # a query's table on the terminal stops here (--json and --csv do not)


class QueryError(RuntimeError):
    """A query the index cannot answer; one line."""


class Index:
    """The index of one store, ready for SQL: `connect()` gives a DuckDB connection with the two views.
    `skipped` lists (file, why) for the index files that are no index of ours (corrupt, hostile, of
    another shape): they are left out, each said in one line, and the rest answer."""

    def __init__(self, store: EpisodeStore, cache_dir: pathlib.Path | None = None):
        self.store = store
        self.cache_dir = cache_dir
        self.skipped: list[tuple[str, str]] = []
        self.listed: dict[str, set[str]] = {}      # table -> the store's keys its view was made from

    def files(self, table: str) -> list[pathlib.Path]:
        """The table's Parquet files as local paths (an S3 store's fetched into the cache, each once:
        index files are never rewritten, only added and, compacted, removed)."""
        prefix = f"{INDEX}/{table}/"
        known_bad = len(self.store.bad_keys)
        objects = [m for m in self.store.list(prefix) if str(m["path"]).endswith(".parquet")]
        self.skipped += [(key, "a key the store's client refuses to name (a '..', '.' or empty segment)")
                         for key in self.store.bad_keys[known_bad:]]
        self.listed[table] = {str(m["path"]) for m in objects}
        root = self.store.local_root
        if root is not None:
            return [root / str(m["path"]) for m in objects]
        cache = self.cache_dir or pathlib.Path(tempfile.mkdtemp(prefix="tecdar-index-"))
        self.cache_dir = cache
        out = []
        for m in objects:
            local = cache / str(m["path"])
            if not local.exists() or local.stat().st_size != int(m["size"]):
                if int(m["size"]) > MAX_INDEX_FILE_BYTES:
                    self.skipped.append((str(m["path"]), f"{int(m['size'])} bytes: no index file of ours"))
                    continue
                local.parent.mkdir(parents=True, exist_ok=True)
                tmp = local.with_name(local.name + ".part")
                tmp.write_bytes(self.store.get(str(m["path"])))
                tmp.replace(local)
            out.append(local)
        return out

    def connect(self):
        """A DuckDB connection (in memory) with the views `episodes` and `contacts`."""
        import duckdb
        con = duckdb.connect()
        for table, (columns, key) in TABLES.items():
            files = self._readable(con, table, self.files(table), columns)
            empty = "SELECT " + ", ".join(f'CAST(NULL AS {t}) AS "{n}"' for n, t in columns) + " WHERE false"
            source = f"read_parquet({_sql_list(files)}, union_by_name = true)" if files else f"({empty})"
            present = _columns(con, source)
            cols = ", ".join(f'"{n}"' for n, _ in columns)
            # a column no file has yet (LATER_COLUMNS, in an index older than it) reads as NULL
            inner = ", ".join(f'"{n}"' if n in present else f'CAST(NULL AS {t}) AS "{n}"' for n, t in columns)
            con.execute(f"CREATE VIEW {table} AS SELECT {cols} FROM (SELECT {inner}, row_number() OVER ("
                        f"PARTITION BY {', '.join(key)} ORDER BY uploaded_at DESC) AS _rn FROM {source}) WHERE _rn = 1")
        return con

    def _readable(self, con, table: str, files: list[pathlib.Path], columns: tuple) -> list[str]:
        """The files DuckDB reads together; when it cannot, each one is looked at and the bad left out."""
        names = [str(f) for f in files]
        if not names:
            return []
        try:          # every column read and cast: a corrupt page or a column of another type fails here
            source = f"read_parquet({_sql_list(names)}, union_by_name = true)"
            con.execute(f"SELECT {_casts(columns, 'count', _columns(con, source))} FROM {source}").fetchall()
            return names
        except Exception:
            pass
        good = []
        for name in names:
            why = _problem(con, name, columns)
            if why is None:
                good.append(name)
            else:
                self.skipped.append((name, why))
        return good


def _problem(con, name: str, columns: tuple) -> str | None:
    try:
        described = con.execute(f"DESCRIBE SELECT * FROM read_parquet({_sql_str(name)})").fetchall()
        got = {row[0]: row[1] for row in described}
    except Exception as exc:
        return f"not Parquet ({first_line(exc, 160)})"
    missing = [n for n, _ in columns if n not in got and n not in LATER_COLUMNS]
    if missing:
        return f"no column {missing[0]!r}: not an index file of ours"
    try:
        con.execute(f"SELECT {_casts(columns, 'count', set(got))} FROM read_parquet({_sql_str(name)})").fetchall()
    except Exception as exc:
        return f"a column of another type ({first_line(exc, 160)})"
    return None


def _casts(columns: tuple, aggregate: str, present: set) -> str:
    return ", ".join(f'{aggregate}(CAST("{n}" AS {t}))' for n, t in columns if n in present or n not in LATER_COLUMNS)


def _columns(con, source: str) -> set:
    """The column names `source` (a read_parquet(...) or a subquery) has."""
    return {row[0] for row in con.execute(f"DESCRIBE SELECT * FROM {source}").fetchall()}


def _sql_str(text: str) -> str:
    return "'" + text.replace("'", "''") + "'"


def _sql_list(names: list[str]) -> str:
    return "[" + ", ".join(_sql_str(n) for n in names) + "]"


VANISHED_RETRIES = 5            # an index file compacted away between the listing and the read: listed again


def query(index: Index, sql: str) -> tuple[list[str], list[tuple]]:
    """(column names, rows) of `sql` over the views; QueryError (one line) when DuckDB refuses it."""
    import duckdb
    for attempt in range(VANISHED_RETRIES):
        con = index.connect()
        try:
            cur = con.execute(sql)
            if cur.description is None:
                return [], []
            return [d[0] for d in cur.description], cur.fetchall()
        except duckdb.IOException as exc:   # a file gone since the listing (a compaction): list again
            if attempt == VANISHED_RETRIES - 1:
                raise QueryError(first_line(exc)) from None
        except duckdb.Error as exc:          # SQL it refuses (a parser, binder or conversion error)
            raise QueryError(first_line(exc)) from None
        finally:
            con.close()
    raise AssertionError("unreachable")


def compact(store: EpisodeStore, cache_dir: pathlib.Path | None = None) -> dict[str, int]:
    """Merge each table's files into one new part (written once), then delete the files it read. A file
    written meanwhile is not among them and stays; two compactions at once leave duplicates that the views
    count once, and one whose files the other removed first lists again. Returns the files merged per table."""
    import duckdb
    for attempt in range(VANISHED_RETRIES):
        try:
            return _compact(store, cache_dir)
        except duckdb.IOException:
            if attempt == VANISHED_RETRIES - 1:
                raise StoreError("the index changed under every compaction attempt; try again") from None
    raise AssertionError("unreachable")


def _compact(store: EpisodeStore, cache_dir: pathlib.Path | None) -> dict[str, int]:
    index = Index(store, cache_dir)
    merged = {}
    con = index.connect()
    try:
        bad = {pathlib.Path(f).name for f, _ in index.skipped}
        for table, (columns, _key) in TABLES.items():
            prefix = f"{INDEX}/{table}/"
            # exactly the files the view was made from: one written since is not merged, so it stays
            read = sorted(index.listed.get(table, ()))
            if len(read) < 2:
                merged[table] = 0
                continue
            keep = [key for key in read if pathlib.Path(key).name not in bad]
            with tempfile.TemporaryDirectory(prefix="tecdar-compact-") as tmp:
                out = pathlib.Path(tmp) / "part.parquet"
                con.execute(f"COPY (SELECT * FROM {table}) TO {_sql_str(str(out))} (FORMAT parquet)")
                stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
                store.put_once(f"{prefix}part-{stamp}-{uuid.uuid4().hex[:8]}.parquet", out.read_bytes())
            for key in keep:
                try:
                    store.delete(key)
                except StoreError as exc:
                    log.warning("index file %s not deleted after compaction: %s", key, exc)
            merged[table] = len(keep)
    finally:
        con.close()
    return merged


def table_text(columns: list[str], rows: list[tuple]) -> str:
    """A query's answer as an aligned text table."""
    def cell(v) -> str:
        if v is None:
            return "-"
        if isinstance(v, float):
            return f"{v:.6g}"
        return str(v)
    body = [[cell(v) for v in r] for r in rows[:MAX_ROWS_SHOWN]]
    widths = [max([len(c)] + [len(r[i]) for r in body]) for i, c in enumerate(columns)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(columns, widths)).rstrip()]
    lines += ["  ".join(v.ljust(w) for v, w in zip(r, widths)).rstrip() for r in body]
    if len(rows) > MAX_ROWS_SHOWN:
        lines.append(f"... {len(rows) - MAX_ROWS_SHOWN} more rows (--csv or --json for all)")
    return "\n".join(lines)


__all__ = ["Index", "QueryError", "compact", "query", "table_text"]
