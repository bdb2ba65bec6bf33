"""An object store's listing that a hostile key does not deny whole.

obstore (object_store underneath) refuses a key with a `..`, `.` or empty segment, and it parses a
listing a page (up to 1000 keys) at a time: one such key in an S3 bucket's index prefix failed every
`episodes query`, `fetch` and `compact`. Here the listing goes on around it:
- the refused key is left out and said (its name is in the error);
- the keys after it are listed from an offset past it;
- the keys before it on its page are listed folder by folder: the folders of the prefix (a listing
  with a delimiter), each on its own, the refused key's own folder again the same way.

A listing's prefix is a whole folder (object_store lists by path segments, not characters): where a
refused segment lies directly in the folder being listed, that folder's delimiter listing fails too,
and the keys on a refused key's page before it cannot be sought. Each such page is said in one line
(`unlisted`), never passed over in silence.
"""
from __future__ import annotations

import re

BAD_PATH = re.compile(r'Error parsing Path "([^"]*)"')
MAX_BAD_KEYS = 64          # a prefix with more refused keys than this is refused whole, in one line


class ListingError(Exception):
    """What keeps a prefix from being listed, in one line."""


def list_around_bad_keys(list_page, list_folders, prefix: str, store_prefix: str, bad: list[str],
                         unlisted: list[str]) -> list[dict]:
    """Every object under `prefix` (a folder, ending in "/") that obstore can name. `list_page(prefix,
    offset)` lists; `list_folders(prefix)` gives (its folders, its objects) by a delimiter; both raise
    obstore's error on a refused key. `store_prefix` is the store's own path in its bucket ("" for none),
    which the error's key carries; the refused keys are appended to `bad`, and to `unlisted` a line for each
    page whose keys before its refused one could not be sought."""
    return _list(list_page, list_folders, prefix, None, None, store_prefix, bad, unlisted)


def _list(list_page, list_folders, prefix: str, offset: str | None, before: str | None, store_prefix: str,
          bad: list[str], unlisted: list[str]) -> list[dict]:
    try:
        found = list_page(prefix, offset)
    except Exception as exc:
        key = _refused(exc, prefix, store_prefix, bad)
        found = _before(list_page, list_folders, prefix, offset, key, store_prefix, bad, unlisted)
        if before is None or _past(key) < before:
            found += _list(list_page, list_folders, prefix, _past(key), before, store_prefix, bad, unlisted)
    return [m for m in found if before is None or str(m["path"]) < before]


def _refused(exc: Exception, prefix: str, store_prefix: str, bad: list[str]) -> str:
    """The key obstore refused (kept in `bad`), or ListingError for any other failure."""
    key = _refused_key(exc, store_prefix)
    if key is None or not key.startswith(prefix):
        raise ListingError(str(exc).splitlines()[0] if str(exc) else type(exc).__name__) from None
    if key not in bad:
        bad.append(key)
    if len(bad) > MAX_BAD_KEYS:
        raise ListingError(f"{prefix}: more than {MAX_BAD_KEYS} keys the store's client refuses "
                           f"(the first {bad[0]!r})") from None
    return key


def _before(list_page, list_folders, prefix: str, offset: str | None, key: str, store_prefix: str,
            bad: list[str], unlisted: list[str]) -> list[dict]:
    """The keys after `offset` and before the refused `key` under the folder `prefix`, folder by folder."""
    try:
        folders, objects = list_folders(prefix)
    except Exception as exc:
        # a refused segment in this folder itself (a folder `..`): its keys are said as the pages meet them, and
        # the keys on the refused key's page before it cannot be sought: said too, not passed over in silence
        if _refused_key(exc, store_prefix) is None:
            raise ListingError(str(exc).splitlines()[0] if str(exc) else type(exc).__name__) from None
        note = f"{prefix}: keys before {key} on its listing's page (up to 1000) could not be listed"
        if offset is not None or any(b < key for b in bad):
            if note not in unlisted:
                unlisted.append(note)
        return []
    out = [m for m in objects if str(m["path"]) < key and (offset is None or str(m["path"]) > offset)]
    for folder in folders:
        folder = folder if folder.endswith("/") else folder + "/"
        if folder > key or (offset is not None and folder + "\U0010ffff" <= offset):
            continue            # after the refused key (listed from past it), or before the offset
        out += _list(list_page, list_folders, folder, offset if offset and offset.startswith(folder) else None,
                     key, store_prefix, bad, unlisted)
    return out


def _refused_key(exc: Exception, store_prefix: str) -> str | None:
    """The key obstore refused to name (its error carries the bucket's key), in the store's own terms."""
    m = BAD_PATH.search(str(exc))
    if m is None:
        return None
    key = m.group(1)
    if store_prefix:
        if not key.startswith(store_prefix + "/"):
            return None
        key = key[len(store_prefix) + 1:]
    return key


def _past(key: str) -> str:
    """A key obstore takes that sorts after `key` and after every key sharing its first refused segment
    (`..`, `.` or empty): that segment with a "0" after it ('0' sorts after the '/' that ends a segment)."""
    start = 0
    for seg in key.split("/"):
        if seg in ("", ".", ".."):
            return key[:start] + seg + "0"
        start += len(seg) + 1
    return key + "0"
