"""Command-line entry points: what a user's mistake looks like.

Every command (``vlr-drake ...`` and the ``python -m vlr_drake....`` tools) ends a run that
failed on its input (a bad scenario field, an unknown object, a missing file, a device that
is not there) with one line on stderr naming what is wrong and exit status 2, not a
traceback. Errors that are bugs still show their traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import re
import sys
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path

#: Exceptions that report a problem with the input or the setting, not with the code:
#: bad values, missing files and settings too large for the machine's memory, and the
#: hardware's own errors (a port or camera that cannot be opened).
USER_ERRORS: tuple[type[BaseException], ...] = (ValueError, FileNotFoundError, PermissionError, IsADirectoryError,
                                                NotADirectoryError, MemoryError)


def _hardware_errors() -> tuple[type[BaseException], ...]:
    from vlr_drake.hardware.camera import CameraError
    from vlr_drake.hardware.dynamixel import DynamixelError

    return (CameraError, DynamixelError)


def plain(doc: str) -> str:
    """A module docstring as a command's help text: reST roles and literals as plain words
    as Sphinx shows them (``:class:`~a.b.C``` -> ``C``, ``:meth:`C.f``` -> ``C.f``, double
    backquotes dropped)."""
    doc = re.sub(r":\w+:`~(?:[\w.]*\.)?([^`]+)`", r"\1", doc)  # ~a.b.C -> C, as Sphinx shows it
    doc = re.sub(r":\w+:`([^`]+)`", r"\1", doc)
    return doc.replace("``", "")


def report(prog: str, error: BaseException) -> int:
    """Print ``prog: error: message`` (on one line) to stderr; returns the exit status 2."""
    message = str(error)
    if isinstance(error, MemoryError):  # a setting too large for this machine (e.g. --particles)
        message = f"out of memory: {message or 'an allocation failed'}; ask for less (fewer particles?)"
    print(f"{prog}: error: {' '.join(message.split())}", file=sys.stderr)
    return 2


@contextlib.contextmanager
def warning_lines(prog: str) -> Iterator[None]:
    """Within it, a warning is one line on stderr, ``prog: warning: message`` (Python's own
    form adds the file, line and source of the call; a command's user wants what it says),
    and each message is said once (a setting checked at several places warned at each)."""
    said = set()

    def line(message, category, filename, lineno, line=None):
        text = f"{prog}: warning: {' '.join(str(message).split())}\n"
        if text in said:
            return ""
        said.add(text)
        return text

    saved = warnings.formatwarning
    warnings.formatwarning = line  # not showwarning: a recording catch_warnings still records
    try:
        yield
    finally:
        warnings.formatwarning = saved


#: Signals that end a hardware command by unwinding it, so that its ``finally`` blocks switch
#: the motors' torque off: Ctrl-C, a kill, a closed terminal (Python's defaults for the last
#: two end the process at once, torque on).
STOP_SIGNALS = ("SIGINT", "SIGTERM", "SIGHUP")


class Stopped(BaseException):
    """A hardware command ended by one of :data:`STOP_SIGNALS`. A BaseException, as
    KeyboardInterrupt is: the drivers' handlers of failed I/O (``except Exception``) let it
    through instead of reporting it as a bus error."""

    def __init__(self, name: str):
        super().__init__(name)
        self.name = name


@contextlib.contextmanager
def unwinding_signals() -> Iterator[None]:
    """Within it (in the main thread), the first of :data:`STOP_SIGNALS` raises
    :class:`Stopped` and the ones after it are ignored, so that nothing interrupts the
    clean-up it starts; the previous handlers come back on the way out."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    sigs = [getattr(signal, name) for name in STOP_SIGNALS if hasattr(signal, name)]  # SIGHUP: POSIX only

    def stop(signum, frame):
        for sig in sigs:
            signal.signal(sig, signal.SIG_IGN)
        raise Stopped(signal.Signals(signum).name)

    previous = {sig: signal.signal(sig, stop) for sig in sigs}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def run(prog: str, main: Callable[[], object], hardware: bool = False) -> int:
    """Run ``main()``; 0 when it returns (whatever it returns, unless an int status), 2
    after :func:`report` when it raises one of :data:`USER_ERRORS` (with ``hardware``,
    also the hardware's errors). With ``hardware`` (a command that may drive a real hand),
    Ctrl-C, a kill or a closed terminal unwinds ``main`` (its ``finally`` blocks switch the
    torque off) and ends it with one line and the shell's status for the signal (128 + its
    number)."""
    import signal

    errors = USER_ERRORS + (_hardware_errors() if hardware else ())
    stops = contextlib.nullcontext() if not hardware else unwinding_signals()
    if hardware:  # this run's buses only
        from vlr_drake.hardware.dynamixel import unconfirmed_torque_off

        unconfirmed_torque_off.clear()
    try:
        with warning_lines(prog), stops:
            status = main()
    except errors as e:
        return report(prog, e)
    except Stopped as e:
        from vlr_drake.hardware.dynamixel import unconfirmed_torque_off

        done = ("a real hand's torque is off" if not unconfirmed_torque_off else
                f"torque off NOT confirmed on {', '.join(dict.fromkeys(unconfirmed_torque_off))}: cut the motors' power")
        print(f"{prog}: stopped by {e.name} (closed on the way out: {done})", file=sys.stderr)
        return 128 + int(getattr(signal, e.name))
    return status if isinstance(status, int) and not isinstance(status, bool) else 0  # (True had exited 1)


class _Interrupt:
    """The state of :func:`stop_between_steps`: how deep its blocks are, and the signal that
    asked the loop to stop (None: not asked)."""

    depth = 0
    asked: str | None = None


def clear_interrupt() -> None:
    """Forget a Ctrl-C an earlier command of this process was asked to stop by."""
    _Interrupt.asked = None


def interrupted(stopped) -> bool:
    """Whether a run's ``stopped`` (its reason, or None) says a Ctrl-C stopped it: its
    "interrupted (SIGINT)" (:func:`stop_between_steps`)."""
    return "interrupted (" in str(stopped or "")


def interrupt_asked() -> str | None:
    """The signal ("SIGINT") that asked a loop in :func:`stop_between_steps` to stop after
    its current step, or None. It stays said after the block, for the command to report."""
    return _Interrupt.asked


@contextlib.contextmanager
def stop_between_steps(what: str) -> Iterator[None]:
    """Within it (in the main thread), a first Ctrl-C asks the loop inside to stop after its
    current step (:func:`interrupt_asked`), which then keeps and writes what it has; a second
    one raises KeyboardInterrupt at once. Blocks nest: an inner one shares the outer's state
    (a reproduce's identification stops the table too). Ctrl-C had lost a whole run to a
    KeyboardInterrupt traceback, its outputs never written (a review)."""
    import signal
    import threading

    if not _Interrupt.depth:  # the outermost block: an earlier run's Ctrl-C is forgotten (a stale one had
        _Interrupt.asked = None  # stopped every later task at its first step where SIGINT was ignored)
    if (_Interrupt.depth or threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is signal.SIG_IGN):  # (ignored: a background job's, which a
        _Interrupt.depth += 1  # Ctrl-C meant for the foreground had stopped; a review)
        try:
            yield
        finally:
            _Interrupt.depth -= 1
        return

    def ask(signum, frame):
        if _Interrupt.asked:  # asked again: at once
            signal.signal(signal.SIGINT, previous)
            raise KeyboardInterrupt
        _Interrupt.asked = signal.Signals(signum).name
        print(f"\nCtrl-C: {what} stops after its current step and keeps what it has (Ctrl-C again: at once)",
              file=sys.stderr)

    previous = signal.signal(signal.SIGINT, ask)
    _Interrupt.depth = 1
    try:
        yield
    finally:
        _Interrupt.depth = 0
        signal.signal(signal.SIGINT, previous)


@contextlib.contextmanager
def replacing(path) -> Iterator[Path]:
    """Write a file in one piece: yields a temporary path beside ``path``, which replaces
    ``path`` once the block is done; where the block fails (a full disk, an interruption) the
    temporary file goes and ``path`` keeps what it held. A result written in place had been
    cut to 4,096 bytes of invalid JSON by a full disk, the last run's result lost with it, and
    a 0-byte trace had made a replay of its folder refuse every trace (a review)."""
    import os
    import shutil

    path = Path(os.path.realpath(path))  # a link's target is written, the link kept
    if path.exists() and not path.is_file():  # a device (/dev/null) or a pipe: written into, as it is
        yield path  # (it had been replaced by a regular file; a review)
        return
    temporary = path.with_name(f".{path.name}.partial{path.suffix}")  # (the suffix: savefig's format)
    try:
        yield temporary
        if path.exists():  # the file's permissions kept
            shutil.copymode(path, temporary)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def saved_trace(trace, path, prog: str) -> str | None:
    """``trace.save(path)`` as a string, or where it cannot be written (a full disk) None,
    said in one line: a run's result is kept without its trace (a trace that failed had
    taken the run's result with it; a review)."""
    try:
        return str(trace.save(path))
    except OSError as e:
        print(f"{prog}: warning: the trace could not be written ({path}: {e.strerror}); the run's result is kept",
              file=sys.stderr)
        return None


def count(least: int):
    """An argparse type: an integer >= ``least`` (argparse names the flag in its error)."""

    def parse(text: str) -> int:
        try:
            n = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not an integer") from None
        if n < least:
            raise argparse.ArgumentTypeError(f"must be >= {least}, got {n}")
        return n

    parse.__name__ = f"integer >= {least}"
    return parse


def path_text(text: str) -> str:
    """An argparse type: a path, not empty. An empty one (a script's unset variable, as in
    ``--trace "$T"``) had been taken for no path: the run went on without writing it, or
    without its scenario, and exited 0."""
    if not str(text).strip():
        raise argparse.ArgumentTypeError("an empty path (an unset variable?)")
    return text


path_text.__name__ = "path"


def as_spelled(text, names) -> str:
    """``text`` as one of ``names`` spells it, whatever its case (``nh2`` -> ``NH2``); a text
    that names none of them is returned as it is, for its user to refuse with the list."""
    return {n.lower(): n for n in names}.get(str(text).lower(), text)


def check_not_trace(json_path, traces) -> None:
    """Refuse a ``--json`` that is one of ``traces`` (a run's ``--trace``, or the traces a
    replay reads): one would be written over the other (identify and a diagram run had
    written their JSON over the trace they had just saved)."""
    for trace in traces if json_path else ():
        if trace and Path(trace).resolve() == Path(json_path).resolve():
            raise ValueError(f"--json {json_path} is the trace {trace} too: one would be written over the other")


def check_output(flag: str, path, *, folder: bool = False) -> None:
    """Refuse, before a run, an output path that the run could not write at its end:
    a file where a folder is wanted or the reverse, a file among its parent folders, a
    parent that is not writable, or an existing file that is not. Folders that do not exist
    yet are fine (they are made). Raises ValueError naming ``flag``."""
    import os
    import tempfile

    if path is None or str(path) == "":
        return
    p = Path(path)
    if folder and p.exists() and not p.is_dir():
        raise ValueError(f"{flag}: '{path}' is a file, not a folder")
    if not folder and p.is_dir():
        raise ValueError(f"{flag}: '{path}' is a folder; give a file in it")
    # an existing file the run replaces at its end (its folder writable, a file protected
    # from writing had passed and the finished run's result was lost in a PermissionError)
    if not folder and p.is_file() and not os.access(p, os.W_OK):
        raise ValueError(f"{flag}: '{path}' exists and is not writable")
    for parent in ([p] if folder else []) + list(p.parents):
        if parent.exists():
            if not parent.is_dir():
                raise ValueError(f"{flag}: '{parent}' is a file, so '{path}' cannot be written")
            if not os.access(parent, os.W_OK | os.X_OK):
                raise ValueError(f"{flag}: '{parent}' is not writable")
            try:  # os.access says yes to root on a read-only file system: a file is made and removed
                with tempfile.TemporaryFile(dir=parent):
                    pass
            except OSError as e:
                raise ValueError(f"{flag}: nothing can be written in '{parent}' ({e.strerror})") from None
            return
