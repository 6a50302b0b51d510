"""How the command-line entry points fail: one line naming the field or option, its value and what is allowed, and
exit 2; a traceback only with ``--debug``. Warnings (fem's, the planner's) print as one line ``prog: warning: ...``
too, without Python's source path and code line (``--debug`` keeps Python's format)."""
from __future__ import annotations

import atexit
import contextlib
import errno
import logging
import os
import sys
import traceback
import warnings
from typing import Callable

from core.contracts import PlanError
from fem.scene import SceneError
from robot.truth import TruthError

EXIT_USAGE = 2
EXIT_BROKEN_PIPE = 141     # 128 + SIGPIPE: what a shell reports for a process the closed pipe ended
EXIT_FAILED = 1            # the work failed (not the user's input): a full disk, a driver's error after its stop
# a write the machine refused: not the user's input (exit 2 says "nothing was done, fix the command"), and what was
# written before it stays (a safety review of session 54 filled the disk mid-run: exit 2, or a traceback on --host)
DISK_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EIO, errno.EROFS)


class RunFailed(RuntimeError):
    """Work that started failed for a reason not in the user's input (the message says what, and what was kept)."""


class UsageError(ValueError):
    """A bad option, value or file given by the user; the message names it and what is allowed."""


# The project's own input errors, and what reading a user's file can raise.
USER_ERRORS = (UsageError, SceneError, PlanError, TruthError, OSError, UnicodeDecodeError)


def _quiet_exit(debug: bool) -> None:
    """The one line is said: what a background helper logs while the process ends (a table's dask cluster torn down
    under its build by its exit handler: "Removing worker ... lost scattered data") is not for the user; logging is
    silenced at the exit only (an in-process caller keeps it). ``--debug`` keeps it."""
    if not debug:       # at the exit, before the helpers' own exit handlers (registered earlier, run later)
        atexit.register(logging.disable, logging.CRITICAL)


def guarded(prog: str, run: Callable[[], int], debug: bool = False) -> int:
    """Run ``run``; a user error becomes ``prog: message`` on one line and exit 2, Ctrl-C exit 130. With ``debug`` the
    traceback is printed too."""
    shown = warnings.showwarning
    if not debug:
        def one_line(message, category, filename, lineno, file=None, line=None):
            print(f"{prog}: warning: {' '.join(str(message).split())}", file=file or sys.stderr)
        warnings.showwarning = one_line
    try:
        return int(run() or 0)
    except BrokenPipeError:
        # the reader of the standard output closed it early (`palpate ... | head`): not the user's input, so not exit
        # 2; what the command writes to files is written before its summary. Exit as a shell reports a process ended
        # by SIGPIPE, and point the standard output at /dev/null so the interpreter's own flush at exit stays quiet
        with contextlib.suppress(OSError, ValueError, AttributeError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        _quiet_exit(debug)
        return EXIT_BROKEN_PIPE
    except RunFailed as e:
        if debug:
            traceback.print_exc()
        print(f"{prog}: {' '.join(str(e).split())}", file=sys.stderr)
        _quiet_exit(debug)
        return EXIT_FAILED
    except USER_ERRORS as e:
        if debug:
            traceback.print_exc()
        if isinstance(e, OSError) and e.errno in DISK_ERRNOS:
            print(f"{prog}: {e.filename or 'a file'}: {os.strerror(e.errno)}: the disk failed a read or a write (not "
                  f"the command's input); what was written before is kept (free space or fix the disk, then run the "
                  f"command again: a run resumes)", file=sys.stderr)
            _quiet_exit(debug)
            return EXIT_FAILED
        msg = " ".join(str(e).split()) or type(e).__name__
        if isinstance(e, OSError) and e.filename is not None and str(e.filename) not in msg:
            msg = f"{e.filename}: {msg}"
        print(f"{prog}: {msg}", file=sys.stderr)
        _quiet_exit(debug)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        _quiet_exit(debug)
        return 130
    finally:
        warnings.showwarning = shown
