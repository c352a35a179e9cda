"""Reading an input file with a bound: a regular file of at most `limit` bytes, else an OSError
whose `strerror` says why (so every reader's existing `except OSError` reports it in one line).

`/dev/zero`, a FIFO or a 5 GB "vehicle file" must never be read whole: every command's file
inputs (vehicle files, key files, commands CSVs, recordings) go through here.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path


def read_bounded(path, limit: int) -> bytes:
    """The bytes of `path` if it is a regular file of at most `limit` bytes."""
    path = Path(path)
    # opened without blocking: open() of a FIFO with no writer would wait for one forever
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode):
            raise OSError(errno.EINVAL, "not a regular file (a device, pipe or directory)", str(path))
        # read(n) allocates n bytes up front: ask for what the file holds (one more byte tells a
        # file that grew past the limit meanwhile)
        data = f.read(min(limit, st.st_size) + 1)
    if len(data) > limit:
        raise OSError(errno.EFBIG, f"larger than {limit:,} bytes: not a file of this kind", str(path))
    return data


def read_text_bounded(path, limit: int) -> str:
    """`read_bounded` decoded as UTF-8 (a byte-order mark is not content)."""
    return read_bounded(path, limit).decode("utf-8-sig")
