"""Readers: SAR inputs into the scene store (:func:`ingest`, ``sarship ingest``).

Modules:

- :mod:`~sarship.pipeline.readers.entry`: :func:`ingest` (argument checks, the tile loop of
  file inputs, atomic write); its docstring gives the contract and the attributes written.
- :mod:`~sarship.pipeline.readers.protocol`: what a reader is (:class:`Reader`, the
  :class:`Probe` its ``detect`` sees, the :data:`Source` its ``open`` returns).
- :mod:`~sarship.pipeline.readers.registry`: :data:`READERS`, the one registry, in the order
  of dispatch; :func:`choose`, :func:`register` / :func:`unregister` / :func:`registered`.
- :mod:`~sarship.pipeline.readers.formats`: one reader per format below, wrapping its module.
  Adding one: ``docs/adding-a-reader.md``.
- :mod:`~sarship.pipeline.readers.tiff`: TIFF / GeoTIFF / BigTIFF, GeoTIFF georeference,
  SNAP sidecar.
- :mod:`~sarship.pipeline.readers.image`: PNG / JPEG amplitude.
- :mod:`~sarship.pipeline.readers.npy`: ``.npy`` arrays.
- :mod:`~sarship.pipeline.readers.polsarpro`: PolSARpro C3 / T3 / C2 folders, the covariance
  convention (``C3_BASIS``, ``PAULI_U``, :func:`t3_to_c3`).
- :mod:`~sarship.pipeline.readers.zarr_input`: a Zarr scene as input.
- :mod:`~sarship.pipeline.readers.plan`: which variables a set of sources gives (the ``auto``
  quantity rule, band and channel names).
- :mod:`~sarship.pipeline.readers.writing`: tile-by-tile writing and the looks of a written
  scene.
- :mod:`~sarship.pipeline.readers.common`: the source base class and checks they share.
- :mod:`~sarship.pipeline.readers.limits`: what an input may declare, checked from its headers.
"""

from sarship.pipeline.readers.common import PROBE_SIDE
from sarship.pipeline.readers.entry import INGEST_KINDS, ROW_BAND_BYTES, ingest
from sarship.pipeline.readers.image import GREY_TOLERANCE_DN
from sarship.pipeline.readers.limits import InputLimits
from sarship.pipeline.readers.polsarpro import C3_BASIS, PAULI_U, t3_to_c3
from sarship.pipeline.readers.protocol import BaseReader, Probe, Reader, SceneReader, Source
from sarship.pipeline.readers.registry import READERS, choose, register, registered, unregister
from sarship.pipeline.readers.writing import LOOKS_SAMPLE_SIDE, LOOKS_SAMPLE_TILES, RANK_ONE_TOL

__all__ = [
    "BaseReader",
    "C3_BASIS",
    "GREY_TOLERANCE_DN",
    "INGEST_KINDS",
    "InputLimits",
    "LOOKS_SAMPLE_SIDE",
    "LOOKS_SAMPLE_TILES",
    "PAULI_U",
    "PROBE_SIDE",
    "Probe",
    "READERS",
    "RANK_ONE_TOL",
    "ROW_BAND_BYTES",
    "Reader",
    "SceneReader",
    "Source",
    "choose",
    "ingest",
    "register",
    "registered",
    "t3_to_c3",
    "unregister",
]
