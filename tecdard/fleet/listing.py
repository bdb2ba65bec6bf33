"""An S3 store's listing that a hostile key does not deny whole.

obstore (object_store underneath) refuses a key with a `..`, `.` or empty segment, which S3 allows, and
it parses a listing a page (up to 1000 keys) at a time: one such key in a bucket's index prefix failed
every `episodes query`, `fetch` and `compact`. Where obstore refuses a listing, the same prefix is listed
again through botocore, whose S3 client names any key. The keys obstore cannot name are left out, and
said. The rest answer.
"""
from __future__ import annotations

import re
import urllib.parse

BAD_PATH = re.compile(r'Path "([^"]*)"')    # obstore's words for a key it cannot name
MAX_BAD_KEYS = 64          # a prefix with more refused keys than this is refused whole, in one line


class ListingError(Exception):
    """What keeps a prefix from being listed, in one line."""


def refused_key(exc: Exception) -> str | None:
    """The bucket's key obstore refused to name, from its error; None for any other failure."""
    m = BAD_PATH.search(str(exc))
    return None if m is None else m.group(1)


def nameable(key: str) -> bool:
    """Whether obstore can name `key` (relative to the store): no empty, `.` or `..` segment."""
    return all(seg not in ("", ".", "..") for seg in key.split("/"))


def list_raw(url: str, endpoint: str | None, region: str | None, allow_http: bool, prefix: str,
             bad: list[str]) -> list[dict]:
    """Every object under `prefix` of the S3 store at `url` (s3://bucket/path) as obstore lists them ({path, size,
    last_modified}, path relative to the store), through botocore; the keys obstore cannot name go to `bad`."""
    try:
        import boto3
        from botocore.config import Config
    except ImportError:
        raise ListingError("a key the store's client refuses to name is in the way, and boto3 (the fleet extra) "
                           "is not installed to list around it") from None
    import logging
    logging.getLogger("botocore").setLevel(logging.WARNING)     # its INFO (where it found credentials) is no news
    parts = urllib.parse.urlparse(url)
    bucket, root = parts.netloc, parts.path.strip("/")
    full = f"{root}/{prefix}" if root else prefix
    if (endpoint or "").startswith("http://") and not allow_http:
        raise ListingError(f"{endpoint}: plain HTTP, and store.allow_http is false")
    client = boto3.client("s3", endpoint_url=endpoint or None, region_name=region or None,
                          config=Config(retries={"max_attempts": 3}))
    out: list[dict] = []
    try:
        for page in client.get_paginator("list_objects_v2").paginate(Bucket=bucket, Prefix=full):
            for obj in page.get("Contents", ()):
                key = obj["Key"][len(root) + 1:] if root else obj["Key"]
                if not nameable(key):
                    if key not in bad:
                        bad.append(key)
                    if len(bad) > MAX_BAD_KEYS:
                        raise ListingError(f"{prefix}: more than {MAX_BAD_KEYS} keys the store's client refuses "
                                           f"(the first {bad[0]!r})")
                    continue
                out.append({"path": key, "size": int(obj["Size"]), "last_modified": obj["LastModified"]})
    except ListingError:
        raise
    except Exception as exc:
        raise ListingError(str(exc).splitlines()[0] if str(exc) else type(exc).__name__) from None
    return out
