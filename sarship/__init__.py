"""sarship: ship detection in SAR scenes, calibrated and distributed.

One import root for the whole product:

- :mod:`sarship.pipeline`: science and tiling, pure array code (no cluster, no web);
- :mod:`sarship.workers`: the Dask cluster, GPU pinning, tile routing, the orchestration of a run;
- :mod:`sarship.service`: the HTTP job API, job store, scheduled ingest and web page;
- :mod:`sarship.cli`: the ``sarship`` command line (``python -m sarship``).

Layers import downward only: ``service`` -> ``workers`` -> ``pipeline`` (``tests/test_layers.py``).
The repository keeps the folders ``pipeline/``, ``workers/`` and ``service/`` at its top level;
``pyproject.toml`` installs them under this package (setuptools ``package-dir``).
"""

from sarship.pipeline import __version__

__all__ = ["__version__"]
