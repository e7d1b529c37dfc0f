"""Exceptions raised by the readers and writers of :mod:`msf_torch.io`.

:class:`DataError` is raised for bad input data: it names the file, the 1-based line (when
there is one) and the field, so a user can open the file at the right place. It subclasses
``ValueError`` so generic callers can catch it as one.

:class:`MissingExtraError` is raised when an optional dependency is needed but not installed;
its message names the ``pip install 'msf_torch[extra]'`` command.
"""

from __future__ import annotations

__all__ = ["DataError", "MissingExtraError"]

import os


class DataError(ValueError):
    """Bad input data, located by file, line and field.

    The message reads ``"{path}:{line}: field '{field}': {problem}"``; parts that are
    ``None`` are left out (``"{path}: {problem}"`` when neither line nor field is known).

    Args:
        path: the file (or folder) that holds the bad data.
        problem: what is wrong, in words.
        line: 1-based line number in ``path``, or None (binary files, whole-file problems).
        field: the column, key or field name, or None.

    Attributes:
        path (str), line (int | None), field (str | None), problem (str): as given.

    Example:
        >>> str(DataError("run/imu.csv", "not a number: 'abc'", line=12, field="gyro_x"))
        "run/imu.csv:12: field 'gyro_x': not a number: 'abc'"
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        problem: str,
        *,
        line: int | None = None,
        field: str | None = None,
    ) -> None:
        self.path = os.fspath(path)
        self.problem = problem
        self.line = line
        self.field = field
        super().__init__(self._format())

    def _format(self) -> str:
        where = self.path if self.line is None else f"{self.path}:{self.line}"
        what = self.problem if self.field is None else f"field '{self.field}': {self.problem}"
        return f"{where}: {what}"

    def __reduce__(self):
        """Pickle support (exceptions cross process boundaries in data loaders)."""
        return (_rebuild_data_error, (self.path, self.problem, self.line, self.field))


def _rebuild_data_error(path: str, problem: str, line: int | None, field: str | None):
    return DataError(path, problem, line=line, field=field)


class MissingExtraError(ImportError):
    """An optional dependency is not installed.

    Args:
        package: the import name that is missing, e.g. ``"gtsam"``.
        extra: the ``msf_torch`` extra that installs it, e.g. ``"peers"``.
        purpose: what it is needed for, e.g. ``"the KITTI data shipped with gtsam"``.

    The message reads, e.g. ``"gtsam is not installed (needed for the KITTI data shipped
    with gtsam); install it with: pip install 'msf_torch[peers]'"``. ``name`` (from
    ``ImportError``) is set to ``package``; ``extra`` is kept as an attribute.
    """

    def __init__(self, package: str, extra: str = "peers", purpose: str | None = None) -> None:
        self.extra = extra
        self.purpose = purpose
        needed = f" (needed for {purpose})" if purpose else ""
        message = (
            f"{package} is not installed{needed}; install it with: pip install 'msf_torch[{extra}]'"
        )
        super().__init__(message, name=package)

    def __reduce__(self):
        """Pickle support."""
        return (MissingExtraError, (self.name, self.extra, self.purpose))
