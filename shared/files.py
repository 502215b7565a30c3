"""Files written whole or not at all: every file a reader may open while it is written (checkpoints,
results, run configs, credentials, statistics rewound on resume) goes through
:func:`write_atomically`, so a crash or a full disk leaves the old file or the new one, never half of
one, and no temporary file beside it. numpy-free and torch-free."""

from __future__ import annotations

import errno
import os
import stat
from collections.abc import Callable
from pathlib import Path
from typing import Any

TMP_MARK = ".tmp-"
"""In the name of a temporary file being written (``.<name>.tmp-<pid>``): what a cleaner of
stale temporaries looks for."""


MAX_READ_BYTES = 256 * 2**20
"""The largest user's file :func:`read_regular_file` reads by default: far more than a config, a
card or a pointer holds, room for an evaluation's results with every trajectory or a long loss
log, and less than a checkpoint or a video handed in by mistake."""


def read_regular_file(path: str | Path, max_bytes: int = MAX_READ_BYTES) -> bytes:
    """The bytes of ``path``, a user's file: OSError for anything but a regular file (a folder, a
    FIFO, whose read would wait for a writer that never comes, ``/dev/zero``, which never ends) and
    for one over ``max_bytes``."""
    # non-blocking open: a FIFO with no writer opens at once, to be refused, instead of hanging here
    with open(path, "rb", opener=lambda name, flags: os.open(name, flags | os.O_NONBLOCK)) as fh:
        info = os.fstat(fh.fileno())
        if not stat.S_ISREG(info.st_mode):
            raise OSError(errno.EINVAL, "not a regular file")
        if info.st_size > max_bytes:  # refused before it fills the memory, not after as invalid text
            raise OSError(errno.EFBIG, f"too large: {info.st_size:,} bytes, over the limit of {max_bytes:,} "
                                       "(a checkpoint or other big file where a text file was meant?)")
        return fh.read()


def fsync_path(path: Path) -> None:
    """Flush the file ``path`` to disk (before it is renamed into place), or a folder's entries (after a
    rename in it: the rename is then durable)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def nearest_existing(path: Path) -> Path:
    """``path`` (absolute) if it exists, else the nearest folder above it that does: where a file
    under a folder yet to be made would be written (its disk, its permissions)."""
    at = path.absolute()
    while not at.exists() and at != at.parent:
        at = at.parent
    return at


WRITE_FAILURES = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EIO})
"""The errnos of a write the disk refused (full, over a quota or a file size limit, read-only, failing):
what a service that writes only records may outlive, unlike a missing file or a bug."""


def named(exc: OSError, path: str | Path) -> OSError:
    """``exc``, a failed write, as one naming ``path`` where it names no file: a full disk fails the
    write, not the open, and "[Errno 28] No space left on device" alone says not where."""
    if exc.filename is not None:
        return exc
    what = f"{path} cannot be written: {exc.strerror or exc}"
    return OSError(exc.errno, what) if exc.errno is not None else OSError(what)


def write_atomically(final: str | Path, write: Callable[[Path], Any], *, tag: str | None = None) -> Path:
    """``write(tmp)`` to a temporary file beside ``final``, fsynced and renamed to it: a reader never
    sees half a file. The temporary file is removed when any step fails (a full disk, ``final`` a
    folder). Returns ``final``; a failed write is raised naming it (:func:`named`). ``tag`` ends the
    temporary file's name instead of this process's id: a folder that processes of other machines or
    containers share (whose ids repeat) needs one of its own per writer."""
    final = Path(final)
    tmp = final.with_name(f".{final.name}{TMP_MARK}{os.getpid() if tag is None else tag}")
    try:
        write(tmp)
        fsync_path(tmp)
        os.replace(tmp, final)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise named(exc, final) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_path(final.parent)
    return final


def atomic_write_text(path: str | Path, text: str, *, tag: str | None = None) -> Path:
    """Write ``text`` to ``path`` via :func:`write_atomically`."""
    return write_atomically(path, lambda tmp: tmp.write_text(text), tag=tag)


def ends_torn(path: str | Path) -> bool:
    """Whether ``path`` holds a last line without its newline (a writer killed mid-line, a full disk):
    a line appended to it would be glued on, and read as one damaged line with it."""
    with open(path, "rb") as fh:
        if fh.seek(0, os.SEEK_END) == 0:
            return False
        fh.seek(-1, os.SEEK_END)
        return fh.read(1) != b"\n"


def append_line(path: str | Path, line: str) -> None:
    """Append ``line`` and a newline to a line-per-record file (made when missing), in one write,
    after ending a torn last line (:func:`ends_torn`) so only that line is lost."""
    path = Path(path)
    torn = path.exists() and ends_torn(path)
    try:
        with open(path, "ab") as fh:
            fh.write((("\n" if torn else "") + line + "\n").encode())
    except OSError as exc:  # a full disk: the line lost, or cut short (ended by the next one)
        raise named(exc, path) from None


def save_png(figure: Any, out_path: str | Path, dpi: int) -> Path:
    """A matplotlib ``figure`` as a PNG at ``out_path`` (its folder made), written whole or not at
    all: a report or map being rewritten keeps its old figure when the disk fills."""
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    # the format is named: matplotlib would read it from the temporary file's name
    return write_atomically(out, lambda tmp: figure.savefig(tmp, dpi=dpi, format="png"))
