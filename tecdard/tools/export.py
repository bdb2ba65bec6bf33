"""`tecdard export REC.npz --mcap OUT.mcap`: a recording, with the estimate replayed over it, as an MCAP
file for Foxglove; the writing is tecdard.recording.mcap's, this is its command line."""
from __future__ import annotations

from tecdard.tools.args import BadInput, add_replay_options, checked_method, refused, show_path_error


def add_parser(sub) -> None:
    p = sub.add_parser("export", help="write a recording and its replayed estimate as MCAP for Foxglove")
    add_replay_options(p)
    p.add_argument("--mcap", required=True, help="OUT.mcap (replaced if it exists)")
    p.set_defaults(func=main)


def main(args) -> int:
    """`tecdard export`: exit 0, or 2 with one line."""
    from tecdard.files import OutputError, check_output, replacing
    from tecdard.recording.format import RecordingError
    from tecdard.recording.mcap import ExportError, export_mcap
    from tecdard.recording.replay import ReplayError

    try:
        method = checked_method(args)
        check_output(args.mcap, "--mcap", [args.recording])       # never over the input, and before the replay
        with replacing(args.mcap, "--mcap") as tmp:     # a failed write leaves what was there
            n, found, events = export_mcap(args.recording, tmp, args.config, method, args.ignore_live)
    except (BadInput, ExportError, RecordingError, ReplayError) as exc:
        return refused("export", str(exc))
    except OutputError as exc:
        return refused("export", show_path_error(exc))
    print(f"{args.mcap}: {n} messages ({len(found)} estimates, {len(events)} events)")
    return 0
