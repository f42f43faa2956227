"""sarship science and tiling: pure array code (no web or cluster code).

Modules: :mod:`pipeline.scene` (the Zarr scene store), :mod:`pipeline.readers` (ingest),
:mod:`pipeline.simulate` (scenes with ground truth), :mod:`pipeline.windows` and
:mod:`pipeline.boxsum` (CFAR windows, tiling-invariant window sums),
:mod:`pipeline.detectors` (the detectors), :mod:`pipeline.components` (detections across
tiles), :mod:`pipeline.scoring` (object and pixel scores).
"""

__version__ = "0.1.0"
