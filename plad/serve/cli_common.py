"""What the commands of ``plad`` (:mod:`plad.serve.cli`) share: the usage error, the reading of the user's
shapes and programs, and the checks and writes of output files."""
from __future__ import annotations

import os
from pathlib import Path

from plad.errors import BadInput, one_line


class UsageError(BadInput):
    """A problem with the user's input; printed as one line, exit status 2 (:mod:`plad.errors`)."""


# ---- shapes and output files ----------------------------------------------------------------
def read_shapes(path: str, shape: tuple[int, ...], target: bool = True, frames=None) -> list:
    """The shapes of one file by the one reader (:func:`plad.data.inputs.read_file`): one item per shape, a bad
    shape of a batch an item with its error. A file that gives one item, in error, is a :class:`UsageError`."""
    from plad.data.inputs import quote, read_file

    items = read_file(path, tuple(shape), target=target, frames=frames)
    if len(items) == 1 and items[0].error:
        raise UsageError(f"{quote(path)}: {items[0].error}")
    return items


def check_output(path: str | None, inputs: tuple[str, ...] = ()) -> Path | None:
    """The output file ``path``, checked before any work: not a folder, not one of the ``inputs`` (never written
    over), and in a folder this process can write to. None when no output was asked for."""
    import tempfile

    from plad.data.inputs import quote

    if path is None:
        return None
    out = Path(path)

    def refuse(reason: str):
        return UsageError(f"{quote(path)}: cannot write ({reason})")

    try:
        if out.is_dir():
            raise refuse("it is a folder; name a file")
        if out.exists() and any(_same_file(source, out) for source in inputs):
            raise refuse("it is an input of this command, which is never written over")
        if not out.parent.is_dir():
            raise refuse(f"No such file or directory: no folder {quote(out.parent)}")
        # the real test of a writable folder: create (and remove) a file in it, as the atomic write will
        with tempfile.NamedTemporaryFile(dir=out.parent, prefix=".plad-check-"):
            pass
    except (OSError, ValueError) as err:
        raise refuse(getattr(err, "strerror", None) or one_line(err)) from None
    return out


def _same_file(source: str, out: Path) -> bool:
    """Whether the argument ``source`` (a path, or text such as a program) names the file ``out``."""
    try:
        return Path(source).exists() and os.path.samefile(source, out)
    except (OSError, ValueError):   # not a path at all (too long, a NUL): not that file
        return False


def check_out_dir(path: str, flag: str = "--out") -> None:
    """A folder that runs write into: it exists as a folder, or can be made in the nearest existing folder
    above it (checked before any work; nothing is created here)."""
    from plad.data.inputs import quote

    folder = Path(path)
    probe = folder
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        raise UsageError(f"{flag} {quote(path)}: {quote(probe)} is a file, not a folder")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise UsageError(f"{flag} {quote(path)}: cannot write in {quote(probe)}")


def write_output(out: Path, text: str) -> None:
    """``text`` into ``out`` (atomically); a failure is one line."""
    from plad.data.inputs import quote
    from plad.fsutil import atomic_write_text

    try:
        atomic_write_text(out, text)
    except OSError as err:
        raise UsageError(f"{quote(out)}: cannot write ({err.strerror or err.__class__.__name__})") from None


def quoted(path: object) -> str:
    """``path`` as the messages show it (:func:`plad.data.inputs.quote`)."""
    from plad.data.inputs import quote

    return quote(path)


def checked_beam(check, beam: int) -> int:
    """``--beam``'s value checked by ``check``; a bad one is a :class:`UsageError`."""
    try:
        return check(beam)
    except ValueError as err:
        raise UsageError(f"--beam {beam}: {err}") from None


def program_text(text: str) -> str:
    """A program given on the command line, or the text of a .txt file holding it.

    An argument that can only be a path (no whitespace, and a ``.txt`` suffix or a
    ``/``; no domain's program text looks like that) must name a readable file.
    """
    path = Path(text)
    looks_like_path = not any(c.isspace() for c in text) and (path.suffix == ".txt" or "/" in text)
    try:
        is_file = path.is_file()
    except (OSError, ValueError):   # a program text too long for a file name, or holding a NUL
        is_file = False
    if is_file and (path.suffix == ".txt" or looks_like_path):
        try:
            return path.read_text()
        except (OSError, UnicodeDecodeError) as err:
            raise UsageError(f"{text}: not a readable text file ({err.__class__.__name__})") from None
    if looks_like_path:
        raise UsageError(f"{text}: file not found")
    return text
