"""Reading a file the user names (a scene, a truth, a plan): a regular file of bounded size, or one clear error.

A pipe would block the command for good, ``/dev/zero`` would fill the memory, and a file nested thousands of
levels deep overflowed the TOML and JSON parsers' recursion: each ended in a hang or a traceback (a session-49
review). ``read_user_text`` refuses what is not a regular file or is larger than ``MAX_INPUT_BYTES``; the parsers'
``RecursionError`` is turned into the caller's own error with ``NESTED_TOO_DEEP``."""
from __future__ import annotations

import os
import stat
from pathlib import Path

MAX_INPUT_BYTES = 64 * 2 ** 20      # a plan of 2000 probes is about 1 MB, a scene file a few hundred bytes
NESTED_TOO_DEEP = "nested too deeply to be a palpate file"


class InputFileError(OSError):
    """A named input that cannot be read as a file: the message names it (``what path: reason``), ``reason`` is the
    why alone (for a caller that names the option itself)."""

    def __init__(self, what: str, path, reason: str):
        super().__init__(f"{what} {path}: {reason}")
        self.reason = reason


def read_user_text(path: str | Path, what: str) -> str:
    """The text of ``path`` (UTF-8), which ``what`` names in any error: InputFileError for a missing file, a
    directory, a device or pipe, or a file above MAX_INPUT_BYTES; UnicodeDecodeError for bytes that are not text."""
    p = Path(path)
    try:
        st = os.stat(p)
    except OSError as e:
        raise InputFileError(what, path, f"cannot be read ({e.strerror or e})") from None
    if not stat.S_ISREG(st.st_mode):
        kind = "a directory" if stat.S_ISDIR(st.st_mode) else "a pipe" if stat.S_ISFIFO(st.st_mode) else \
            "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode) else "not a regular file"
        raise InputFileError(what, path, f"is {kind}; give a regular file")
    if st.st_size > MAX_INPUT_BYTES:
        raise InputFileError(what, path, f"{st.st_size} bytes, above the {MAX_INPUT_BYTES} a palpate file may hold")
    try:
        return p.read_text(encoding="utf-8")
    except OSError as e:
        raise InputFileError(what, path, f"cannot be read ({e.strerror or e})") from None
