"""Where the daemon writes (maps, later recordings), and how: private modes, checked at start-up,
complete or not at all (a temporary name, then one rename)."""
from __future__ import annotations

import contextlib
import os
import pathlib
import shutil
import tempfile

DIR_MODE = 0o700               # maps and recordings are the operator's, not the host's
FILE_MODE = 0o600
PARTIAL_PREFIX = ".partial-"   # what a writer killed mid-way leaves; readers skip it, the next start removes it


class OutputError(OSError):
    """A directory the daemon must write to cannot be used: `what` (the option naming it) and why."""

    def __init__(self, what: str, reason: str):
        super().__init__(f"{what}: {reason}")
        self.what, self.reason = what, reason


def state_dir() -> pathlib.Path:
    """systemd's StateDirectory when run as the service, else the user's state directory
    ($XDG_STATE_HOME/tecdar, ~/.local/state/tecdar): never the working directory."""
    state = os.environ.get("STATE_DIRECTORY")
    if state:
        return pathlib.Path(state.split(":")[0])
    xdg = os.environ.get("XDG_STATE_HOME")
    base = pathlib.Path(xdg) if xdg and os.path.isabs(xdg) else pathlib.Path.home() / ".local" / "state"
    return base / "tecdar"


def ensure_writable_dir(path: str | os.PathLike, what: str) -> pathlib.Path:
    """Create `path` (mode 0700) if needed and prove it writable now, not at the end of a task;
    OutputError naming `what` otherwise. Leftovers of writers killed mid-way are removed."""
    p = pathlib.Path(path)
    try:
        p.mkdir(mode=DIR_MODE, parents=True, exist_ok=True)
        if not p.is_dir():
            raise OutputError(what, f"{p} is not a directory")
        with tempfile.NamedTemporaryFile(dir=p, prefix=PARTIAL_PREFIX):
            pass
    except OutputError:
        raise
    except OSError as exc:
        raise OutputError(what, f"{p} is not writable ({exc.strerror or type(exc).__name__})") from None
    for stale in p.glob(PARTIAL_PREFIX + "*"):
        shutil.rmtree(stale, ignore_errors=True) if stale.is_dir() else stale.unlink(missing_ok=True)
    return p


@contextlib.contextmanager
def atomic_dir(final: str | os.PathLike):
    """Yield a private temporary directory beside `final`; on success its files are synced and it
    is renamed to `final` in one step, so a reader sees the whole directory or none of it. On an
    exception (or a kill) only the temporary directory is left, named PARTIAL_PREFIX..."""
    final = pathlib.Path(final)
    tmp = pathlib.Path(tempfile.mkdtemp(prefix=PARTIAL_PREFIX + final.name + "-", dir=final.parent))
    try:
        yield tmp
        for f in tmp.iterdir():
            os.chmod(f, FILE_MODE)
            with open(f, "rb") as fh:
                os.fsync(fh.fileno())
        os.chmod(tmp, DIR_MODE)
        os.replace(tmp, final) if not final.exists() else _replace_dir(tmp, final)
        fd = os.open(final.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _replace_dir(tmp: pathlib.Path, final: pathlib.Path) -> None:
    """`final` exists (a map written again under the same task id): move it aside, then swap."""
    old = final.with_name(PARTIAL_PREFIX + final.name + "-old")
    shutil.rmtree(old, ignore_errors=True)
    os.replace(final, old)
    os.replace(tmp, final)
    shutil.rmtree(old, ignore_errors=True)


# -- what the offline tools write ---------------------------------------------------------

def check_output(out: str | os.PathLike, option: str, inputs=()) -> pathlib.Path:
    """An output path a tool may write, checked before any work: not one of its `inputs` (the same
    file under any name), not a directory, in a directory that exists and can be written.
    OutputError naming `option` otherwise."""
    path = pathlib.Path(out)
    for given in inputs:
        same = path.exists() and os.path.exists(given) and os.path.samefile(path, given)
        if same or os.path.abspath(path) == os.path.abspath(given):
            raise OutputError(option, f"{out} is the input {given}: refused (it would be overwritten); "
                                      "write the output elsewhere")
    if path.is_dir():
        raise OutputError(option, f"cannot write {out} (a directory)")
    parent = path.parent if str(path.parent) else pathlib.Path(".")
    if not parent.is_dir():
        raise OutputError(option, f"cannot write {out} (no directory {parent})")
    if path.exists() and not path.is_file():
        if not os.access(path, os.W_OK):
            raise OutputError(option, f"cannot write {out} (permission denied)")
    elif not os.access(parent, os.W_OK):
        raise OutputError(option, f"cannot write {out} (directory {parent} not writable)")
    return path


@contextlib.contextmanager
def replacing(out: str | os.PathLike, option: str):
    """Write a tool's output whole or not at all: yields the path to write. A regular file (new, or
    one that is there) is written under a temporary name beside it and renamed over it once
    complete, so a failed write (a full disk, an exception) leaves what was there as it was; for
    a device or a FIFO (/dev/null, /dev/stdout) the output is made in the temporary directory and
    then copied to it. Any failure is OutputError naming `option`, with the reason in one line."""
    path = pathlib.Path(out)
    device = path.exists() and not path.is_file()
    folder = tempfile.gettempdir() if device else (path.parent if str(path.parent) else ".")
    fd, tmp = tempfile.mkstemp(prefix=PARTIAL_PREFIX + path.name + "-", suffix=path.suffix, dir=folder)
    os.close(fd)
    try:
        yield pathlib.Path(tmp)
        if device:
            with open(tmp, "rb") as src, open(path, "wb") as dst:
                shutil.copyfileobj(src, dst)
            os.unlink(tmp)
            return
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(tmp, 0o666 & ~mask)               # as a plain open() would have made it
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError) and not isinstance(exc, OutputError):
            raise OutputError(option, f"writing {out} failed ({exc.strerror or exc})") from None
        raise
