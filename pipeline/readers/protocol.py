"""What a reader is: the :class:`Reader` protocol the ingest entry point dispatches on, the
:class:`Probe` a reader's ``detect`` looks at, and :class:`BaseReader` with the defaults most
readers keep.

A reader turns one input (a file or a folder) into a :data:`Source` that the tile loop of
:func:`sarship.pipeline.readers.ingest` reads window by window. The entry point asks the
readers of :data:`sarship.pipeline.readers.registry.READERS`, in order, whether an input is
theirs (``detect``) and opens it with the first that says yes. How to add one:
``docs/adding-a-reader.md``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Protocol, runtime_checkable

from sarship.pipeline.errors import InputError
from sarship.pipeline.readers.common import _one_line, _Source
from sarship.pipeline.readers.limits import InputLimits

#: What a reader's ``open`` returns: one input, read window by window (``read``), with its
#: shape, bands, sample type and metadata (see :class:`sarship.pipeline.readers.common._Source`).
Source = _Source

#: Bytes of a file's start that a :class:`Probe` reads (the longest magic number is 8 bytes).
HEAD_BYTES = 16


class Probe:
    """One input as the readers' ``detect`` see it: its path, whether it is a folder, and (for
    a file) its first :data:`HEAD_BYTES` bytes, read once on first use.

    Parameters
    ----------
    path : Path
        The input as given.
    """

    def __init__(self, path: Path):
        self.path = path
        self.is_dir = path.is_dir()
        self._head: bytes | None = None

    @property
    def head(self) -> bytes:
        """The file's first bytes.

        Raises
        ------
        InputError
            The file cannot be opened, or is empty (the input is then nobody's).
        """
        if self._head is None:
            try:
                with open(self.path, "rb") as f:
                    head = f.read(HEAD_BYTES)
            except OSError as exc:
                raise InputError(f"'{self.path}': cannot open ({_one_line(exc)})") from None
            if not head:
                raise InputError(f"'{self.path}' is empty")
            self._head = head
        return self._head


@runtime_checkable
class Reader(Protocol):
    """One input format.

    Attributes
    ----------
    name : str
        Short lowercase name; unique in the registry. A failure inside ``open`` that is not an
        :class:`InputError` is reported as ``'PATH': cannot read as NAME (...)``.
    alone : str or None
        ``None`` when the input may be stacked with other inputs (bands of one scene); else the
        refusal said when it is combined with others (e.g. ``"a PolSARpro folder cannot be
        combined with other inputs"``).
    takes_swath : bool
        Whether ``--swath`` applies (Sentinel-1 SLC); other readers refuse it.
    """

    name: str
    alone: str | None
    takes_swath: bool

    def detect(self, probe: Probe) -> bool:
        """Whether the input is this format. Cheap: names, layout, ``probe.head``; never pixels.
        May raise :class:`InputError` for an input that is plainly meant for this reader but
        cannot be (e.g. a PolSARpro ``config.txt`` without its ``C11.bin``)."""
        ...

    def check(self, path: Path, kind: str) -> None:
        """Refuse a ``--kind`` that does not fit the input, before anything is opened."""
        ...

    def open(
        self, path: Path, limits: InputLimits, *, sidecar_root: Path | bool | None = None, swath: str | None = None
    ) -> Source:
        """The input as a :data:`Source`, its declared size checked against ``limits`` before
        any pixel is decoded (``limits.check_pixels`` and, for compressed data, the chunk and
        ratio checks of :class:`~sarship.pipeline.readers.limits.InputLimits`)."""
        ...


@runtime_checkable
class SceneReader(Reader, Protocol):
    """A reader whose input is already a whole scene (a Zarr scene): ``ingest`` copies it to
    ``out`` instead of the tile loop over sources. Such a reader is never combined."""

    def ingest(
        self,
        path: Path,
        out: Path,
        *,
        tile: int,
        progress: Callable[[int, int], None],
        looks: float | None,
        codec: str,
        spacing: list[float] | None,
        limits: InputLimits,
    ) -> None:
        """Write the scene ``out`` from the scene ``path`` (atomic, as the tile loop)."""
        ...


class BaseReader:
    """Defaults of a :class:`Reader`: combined with others, no ``--swath``, every ``--kind``.

    A subclass sets ``name`` and writes ``detect`` and ``open``.
    """

    name: str = ""
    alone: str | None = None
    takes_swath: bool = False

    def detect(self, probe: Probe) -> bool:  # pragma: no cover - every reader writes its own
        raise NotImplementedError

    def check(self, path: Path, kind: str) -> None:
        """Every ``--kind`` is accepted here (the sample-type rules are the plan's)."""

    def open(
        self, path: Path, limits: InputLimits, *, sidecar_root: Path | bool | None = None, swath: str | None = None
    ) -> Source:  # pragma: no cover - every reader writes its own
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"<reader {self.name}>"
