"""Ctrl-C during a CasADi solve: CasADi turns a KeyboardInterrupt raised inside IPOPT into a failed solve (status
``NonIpopt_Exception_Thrown`` or ``User_Requested_Stop``) and the interrupt is gone, so ``palpate plan`` exited 0 and
``palpate run`` went on to probe. ``interruptible(call)`` notes a SIGINT that arrives during ``call`` and raises
KeyboardInterrupt once the call returns (in the main thread with Python's own handler installed; elsewhere the call
runs unchanged: a handler can only be set there, and a caller's own handler is left alone)."""
from __future__ import annotations

import signal
import threading
from typing import Callable, TypeVar

T = TypeVar("T")


def interruptible(call: Callable[[], T]) -> T:
    """``call()``, then KeyboardInterrupt if SIGINT arrived meanwhile (the handler still raises it at once, so IPOPT
    stops at its next check)."""
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        return call()
    seen = []

    def handler(signum, frame):
        seen.append(signum)
        raise KeyboardInterrupt
    try:
        signal.signal(signal.SIGINT, handler)      # inside: a SIGINT right after it still reaches the finally
        out = call()
    except Exception:
        if seen:           # CasADi may also wrap it: "Error in Function::call ... KeyboardInterrupt"
            raise KeyboardInterrupt from None
        raise
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)     # what was there (checked above)
    if seen:
        raise KeyboardInterrupt
    return out
