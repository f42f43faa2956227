"""sarship science and tiling: pure array code (no web or cluster code).

Modules: :mod:`sarship.pipeline.scene` (the Zarr scene store), :mod:`sarship.pipeline.readers` (ingest),
:mod:`sarship.pipeline.simulate` (scenes with ground truth), :mod:`sarship.pipeline.windows` and
:mod:`sarship.pipeline.boxsum` (CFAR windows, tiling-invariant window sums),
:mod:`sarship.pipeline.detectors` (the detectors), :mod:`sarship.pipeline.components` (detections across
tiles), :mod:`sarship.pipeline.scoring` (object and pixel scores).
"""

__version__ = "0.1.0"
