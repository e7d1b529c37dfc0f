"""Atomic file writes: a file is either fully written or left as it was.

Writers in :mod:`msf_torch.io` go through :func:`atomic_write`, so an exception (or a
crash) in the middle of a write never leaves a truncated output file behind and never
destroys the previous version of the file.
"""

from __future__ import annotations

__all__ = ["atomic_write", "atomic_save_npz"]

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np


def _default_mode_bits(target: Path) -> int:
    """Permission bits for a new file: the existing target's, else 0o666 minus the umask."""
    try:
        return target.stat().st_mode & 0o7777
    except FileNotFoundError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike[str], mode: str = "w", **kw: Any) -> Iterator[IO[Any]]:
    """Open a temporary file next to ``path``; on success move it onto ``path``.

    Missing parent folders of ``path`` are created first. The temporary file lives in the
    same folder (so ``os.replace`` is an atomic rename on
    POSIX and Windows). If the ``with`` body raises, the temporary file is removed and the
    target is untouched. The new file gets the old file's permission bits, or the usual
    ``0o666 & ~umask`` for a new file.

    Args:
        path: target file; its parent folders are created when missing.
        mode: ``"w"``/``"wt"`` (text, the default) or ``"wb"`` (binary); ``"x"`` and ``"a"``
            are not supported.
        **kw: passed to ``open`` (e.g. ``newline=""``); text mode defaults to
            ``encoding="utf-8"``.

    Yields:
        the open file object.

    Raises:
        OSError: the folder cannot be created or written (the message names ``path``, not
            the temporary file).

    Example:
        >>> with atomic_write(tmp / "out.txt") as f:  # doctest: +SKIP
        ...     f.write("hello\\n")
    """
    if mode not in ("w", "wt", "wb"):
        raise ValueError(f"atomic_write supports modes 'w', 'wt' and 'wb', got {mode!r}")
    target = Path(path)
    if "b" not in mode:
        kw.setdefault("encoding", "utf-8")
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        problem = f"cannot create the folder {target.parent} of {target}: {err.strerror}"
        raise OSError(err.errno, problem) from err
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    except OSError as err:
        raise OSError(err.errno, f"cannot write {target}: {err.strerror}") from err
    try:
        with os.fdopen(fd, mode, **kw) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(tmp_name, _default_mode_bits(target))
        os.replace(tmp_name, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        raise


def atomic_save_npz(path: str | os.PathLike[str], **arrays: Any) -> None:
    """Save arrays into an uncompressed ``.npz`` at ``path``, atomically.

    Args:
        path: target file, written exactly as given (no ``.npz`` is appended).
        **arrays: name -> array-like; names may contain ``/``.
    """
    with atomic_write(path, "wb") as handle:
        np.savez(handle, **{k: np.asarray(v) for k, v in arrays.items()})
