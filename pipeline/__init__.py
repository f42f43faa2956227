"""sarship science and tiling: pure array code (no web or cluster code).

Subpackages, by concern:

- :mod:`sarship.pipeline.readers`: ingest of every input format into the scene store
  (:mod:`sarship.pipeline.scene`);
- :mod:`sarship.pipeline.simulate`: scenes with ground truth;
- :mod:`sarship.pipeline.tiling`: halo windows, tiling-invariant window sums, per-tile inputs;
- :mod:`sarship.pipeline.stats`: clutter distributions, their fits and tail quantiles;
- :mod:`sarship.pipeline.image`: whole-image steps (destriping, superpixels);
- :mod:`sarship.pipeline.land`: land masks (texture, coastline, files);
- :mod:`sarship.pipeline.detectors`: the detectors and their registry;
  :mod:`sarship.pipeline.gpu`: their GPU twins;
- :mod:`sarship.pipeline.targets`: from a mask to ships (components, features, sidelobes, ambiguities,
  geolocation);
- :mod:`sarship.pipeline.run`: a run as a plan and typed stages;
- :mod:`sarship.pipeline.products`: truth, scores and exports;
- :mod:`sarship.pipeline.ais`: AIS reports, tracks and their matching to detections.

Beside them: :mod:`sarship.pipeline.errors` (one-line user errors) and
:mod:`sarship.pipeline.settings` (every ``SARSHIP_*`` variable read below the service).
"""

__version__ = "0.1.0"
