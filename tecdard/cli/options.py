"""`tecdard options [SECTION]`: every config option, with its default, unit, limits and what it does, generated
from the declarations (tecdard.options) that the config reader reads them through; `--markdown` writes
docs/options.md. `tecdard run --help` ends with the same list."""
from __future__ import annotations

import sys

from tecdard.runtime.option_sections import sections

MARKDOWN_HEAD = """# Config options

Every option of a `tecdard run` config, generated from the declarations the daemon reads them through
(`tecdard options --markdown`; tests/test_layout.py holds this page to them). Units are SI unless named;
`limits` are checked at start, and a key nobody declares is an error (a typo never passes silently).
`tecdard options SECTION` prints one section for a terminal. The shipped configs (`configs/sim.yaml`,
`ur5e.yaml`, `fr3.yaml`) set the ones a rig usually changes.
"""


def merged() -> list[tuple[str, list[type]]]:
    """The sections with the classes that read each (zenoh's rates and security beside its own)."""
    out: dict[str, list[type]] = {}
    for path, cls in sections():
        out.setdefault(path, []).append(cls)
    return list(out.items())


def markdown() -> str:
    from tecdard.options import cells, rows
    out = [MARKDOWN_HEAD]
    for path, classes in merged():
        out += [f"## `{path}`", "", "| option | default | unit | limits | what it does |", "|---|---|---|---|---|"]
        out += [cells(row) for cls in classes for row in rows(path, cls)]
        out.append("")
    return "\n".join(out)


def text(only: str | None = None) -> str:
    from tecdard.options import text as lines
    return lines(sections(), only)


def main(args) -> int:
    if args.markdown:
        sys.stdout.write(markdown())
        return 0
    known = {path for path, _ in sections()}
    if args.section and not any(p == args.section or p.startswith(args.section + ".") for p in known):
        print(f"tecdard options: no section {args.section!r} (known: {', '.join(sorted(known))})", file=sys.stderr)
        return 2
    print(text(args.section))
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("options", help="every config option: default, unit, limits and what it does",
                       description="Every option of the daemon's config, generated from the declarations it is read "
                                   "through (docs/options.md is the same, as tables).")
    p.add_argument("section", nargs="?", help="only this section and those under it (e.g. control, estimator.ekf)")
    p.add_argument("--markdown", action="store_true", help="the tables of docs/options.md")
    p.set_defaults(func=main)
