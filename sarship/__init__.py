"""sarship: ship detection in SAR scenes, calibrated and distributed.

One import root for the whole product:

- :mod:`sarship.pipeline`: science and tiling, pure array code (no cluster, no web);
- :mod:`sarship.workers`: the Dask cluster, GPU pinning, tile routing, the orchestration of a run;
- :mod:`sarship.service`: the HTTP job API, job store, scheduled ingest and web page;
- :mod:`sarship.cli`: the ``sarship`` command line (``python -m sarship``).

Layers import downward only: ``service`` -> ``workers`` -> ``pipeline`` (``tests/test_layers.py``).
The repository keeps the folders ``pipeline/``, ``workers/`` and ``service/`` at its top level;
``pyproject.toml`` installs them under this package (setuptools ``package-dir``). Every process
of a Dask cluster must run the same sarship version (docs/architecture.md).
"""

from pathlib import Path as _Path

_checkout = _Path(__file__).resolve().parent.parent
if (_checkout / "pyproject.toml").is_file() and (_checkout / "pipeline" / "__init__.py").is_file():
    # Imported from a source checkout (``python -m sarship`` or ``python -m pytest`` in the
    # repository folder, which puts that folder first on sys.path): its top-level folders are
    # the subpackages, as the editable install maps them, so a checkout never mixes with an
    # installed copy of another version. An installed sarship has no pyproject.toml beside it.
    __path__.append(str(_checkout))  # noqa: F821 (a package's __path__)

from sarship.pipeline import __version__  # noqa: E402

__all__ = ["__version__"]
