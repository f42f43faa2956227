"""A detection run as a declared sequence of typed stages (docs/architecture.md, "A run").

``plan`` (the request parsed and checked once), ``merge`` (the rules on whole detections),
``refine`` (features, contrast, sidelobes, geolocation, ambiguities), ``fit`` (the clutter-model
fit record), ``record`` (``run.json``), ``outputs`` (the output folder: checked, written under a
temporary name, published). Pure array code and file I/O: the Dask execution of the stages is
:mod:`sarship.workers.jobs`.
"""
