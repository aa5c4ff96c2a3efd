"""One exit-code convention for the ``plad`` command line and the stage commands.

* 0 (:data:`OK`): the command did what was asked;
* 1 (:data:`FAILURE`): the run or its data failed: a missing or damaged
  dataset, a model that cannot be found or used (a checkpoint given with
  ``--model`` or shipped, an MLflow model URI, no model at all), an MLflow
  store that cannot be reached, a params file with a bad key or value, a stage
  whose inputs are not there yet;
* 2 (:data:`USAGE`): bad usage or input: a command-line argument (a beam out of
  range, an output path that cannot be written), a program text, a shape given
  on the command line (argparse uses 2 as well). A command that processes
  several shapes (``plad infer`` on a folder, ``plad search`` or ``score`` on a
  batch) writes every good result and then exits 2 when any shape was refused.

This is the one place the convention is written; the commands' documentation refers here.

Each error class a user can cause derives from :class:`RunFailure` or
:class:`BadInput` and so carries its status; :func:`run_guarded` is where the
CLI and every stage's ``main()`` turn such an error into one line on stderr
and its status. So is an ``OSError`` of the machine rather than of the code
(:data:`ENVIRONMENT_ERRNOS`: a full disk, a read-only or unwritable place, a
name too long): one line naming the file and the cause, status 1 (every
output is written by :func:`plad.fsutil.atomic_write`, so the old files are
intact). Anything else is a bug and keeps its traceback.
"""
from __future__ import annotations

import errno
import sys
from collections.abc import Callable

OK = 0
FAILURE = 1
USAGE = 2


class PladError(Exception):
    """An error a user can fix; ``str(err)`` is one line. ``exit_code`` is the command's status."""

    exit_code = FAILURE


class RunFailure(PladError):
    """The run or its data failed (exit status 1)."""

    exit_code = FAILURE


class BadInput(PladError):
    """Bad usage or input on the command line (exit status 2)."""

    exit_code = USAGE


def one_line(text: object) -> str:
    return " ".join(str(text).split())


def fail(prog: str, message: object, status: int) -> int:
    """Print ``<prog>: error: <message>`` as one line on stderr; return ``status``."""
    print(f"{prog}: error: {one_line(message)}", file=sys.stderr)
    return status


#: the errors of the machine a command runs on, not of its code: one line, never a traceback
ENVIRONMENT_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG,
                                errno.ENAMETOOLONG, errno.EMFILE, errno.ENFILE, errno.EIO})


def describe_os_error(err: OSError) -> str:
    """An ``OSError`` in one line: ``cannot use '<file>': <cause>``."""
    name = err.filename if err.filename is not None else ""
    shown = str(name) if str(name).isprintable() else repr(str(name))
    cause = err.strerror or one_line(err) or err.__class__.__name__
    return f"cannot use {shown}: {cause}" if name != "" else cause


def run_guarded(prog: str, fn: Callable[[], int | None], describe: Callable[[PladError], str] = str) -> int:
    """``fn()``'s status (None: :data:`OK`); a :class:`PladError` becomes one line and its ``exit_code``, and so
    does an ``OSError`` of :data:`ENVIRONMENT_ERRNOS` (status :data:`FAILURE`)."""
    try:
        status = fn()
    except PladError as err:
        return fail(prog, describe(err), err.exit_code)
    except OSError as err:
        if err.errno not in ENVIRONMENT_ERRNOS:
            raise
        return fail(prog, describe_os_error(err), FAILURE)
    return OK if status is None else status
