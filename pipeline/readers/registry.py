"""The one registry of readers: :data:`READERS`, in the order of dispatch, and :func:`choose`,
which the ingest entry point (:mod:`sarship.pipeline.readers.entry`) calls for every input.

The order is the documented precedence (``docs/adding-a-reader.md``):

1. ``safe``: a folder with ``manifest.safe``, or a ``.zip`` holding one SAFE product;
2. ``polsarpro``: a PolSARpro folder (not a Zarr scene), its ``config.txt``, ``C11.bin`` or
   ``T11.bin``;
3. ``zarr``: a folder with ``zarr.json`` or ``.zgroup``;
4. ``tiff``, 5. ``image`` (PNG, JPEG), 6. ``npy``: files by their first bytes.

An input no reader takes is refused by :func:`refuse` (one line naming it and what was
expected). The same order decides which refusal is said when inputs that must stand alone
(``Reader.alone``) are combined.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import NoReturn

from sarship.pipeline.errors import InputError
from sarship.pipeline.readers.formats import ImageReader, NpyReader, PolsarproReader, SafeReader, TiffReader, ZarrReader
from sarship.pipeline.readers.protocol import Probe, Reader

#: The readers, in the order of dispatch: the first whose ``detect`` says yes opens the input.
READERS: list[Reader] = [SafeReader(), PolsarproReader(), ZarrReader(), TiffReader(), ImageReader(), NpyReader()]


def reader_names() -> list[str]:
    """The registered readers' names, in the order of dispatch."""
    return [r.name for r in READERS]


def register(reader: Reader, before: str | None = None) -> None:
    """Add ``reader`` to :data:`READERS`: last, or just before the reader named ``before``.

    Raises
    ------
    ValueError
        A reader of that name is registered already, or ``before`` names none.
    """
    names = reader_names()
    if reader.name in names:
        raise ValueError(f"a reader named '{reader.name}' is registered already")
    if before is None:
        READERS.append(reader)
    elif before in names:
        READERS.insert(names.index(before), reader)
    else:
        raise ValueError(f"no reader named '{before}' (registered: {', '.join(names)})")


def unregister(name: str) -> Reader:
    """Remove the reader named ``name`` from :data:`READERS` and return it.

    Raises
    ------
    KeyError
        No reader of that name is registered.
    """
    for i, r in enumerate(READERS):
        if r.name == name:
            return READERS.pop(i)
    raise KeyError(name)


@contextmanager
def registered(reader: Reader, before: str | None = None) -> Iterator[Reader]:
    """``reader`` registered (:func:`register`) for the ``with`` block, unregistered after it."""
    register(reader, before)
    try:
        yield reader
    finally:
        unregister(reader.name)


def refuse(probe: Probe) -> NoReturn:
    """Raise the :class:`InputError` for an input no reader takes."""
    p = probe.path
    if probe.is_dir:
        raise InputError(
            f"'{p}' is a folder but not a Zarr scene (no zarr.json), a PolSARpro "
            "C3/T3/C2 folder (no C11.bin or T11.bin) nor a Sentinel-1 SAFE product (no manifest.safe)"
        )
    if probe.head[:4] == b"PK\x03\x04" and p.suffix.lower() == ".npz":
        raise InputError(f"'{p}': .npz archives are not supported; save one array with np.save")
    raise InputError(
        f"'{p}': unrecognised format (expected TIFF/GeoTIFF, PNG, JPEG, .npy, a Sentinel-1 SAFE folder/zip "
        "or a Zarr scene)"
    )


def choose(path: Path) -> Reader:
    """The first reader of :data:`READERS` whose ``detect`` takes ``path``.

    Raises
    ------
    InputError
        No reader takes it (:func:`refuse`), or one found it plainly meant for it but unusable.
    """
    probe = Probe(path)
    for reader in READERS:
        if reader.detect(probe):
            return reader
    refuse(probe)
