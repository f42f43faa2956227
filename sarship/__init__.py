"""sarship: ship detection in SAR scenes, calibrated and distributed.

One import root for the whole product:

- :mod:`sarship.pipeline`: science and tiling, pure array code (no cluster, no web);
- :mod:`sarship.workers`: the Dask cluster, GPU pinning, tile routing, the orchestration of a run;
- :mod:`sarship.service`: the HTTP job API, job store, scheduled ingest and web page;
- :mod:`sarship.cli`: the ``sarship`` command line (``python -m sarship``).

Layers import downward only: ``service`` -> ``workers`` -> ``pipeline`` (``tests/project/test_layers.py``).
The repository keeps the folders ``pipeline/``, ``workers/`` and ``service/`` at its top level;
``pyproject.toml`` installs them under this package (setuptools ``package-dir``). Every process
of a Dask cluster must run the same sarship version (docs/architecture.md).

Importing this package sets ``NUMBA_CACHE_DIR`` (unless set) to a user cache folder
(:func:`numba_cache_dir`), so that no sarship process writes Numba's caches into site-packages
or the source tree.
"""

import os as _os
import sys as _sys
from collections.abc import Mapping as _Mapping
from pathlib import Path as _Path


def numba_cache_dir(environ: _Mapping[str, str] = _os.environ) -> _Path:
    """The folder where sarship's processes keep Numba's compiled functions (``cache=True``).

    A user cache folder, never next to the installed modules: Numba's default writes its
    ``*.nbi`` / ``*.nbc`` files into ``__pycache__`` beside the source, where ``pip uninstall``
    does not know them, and the ``site-packages/sarship/`` folder they keep then shadows an
    editable install of sarship (issue 30). The first writable of ``$XDG_CACHE_HOME/sarship/numba``,
    ``~/.cache/sarship/numba`` and ``TMPDIR/sarship-UID/numba``.

    Parameters
    ----------
    environ : mapping
        The environment to read ``XDG_CACHE_HOME`` and ``HOME`` from.

    Returns
    -------
    pathlib.Path
        The folder (created; the temporary one even where it could not be created).
    """
    candidates = []
    if environ.get("XDG_CACHE_HOME", "").strip():
        candidates.append(_Path(environ["XDG_CACHE_HOME"]) / "sarship" / "numba")
    if environ.get("HOME", "").strip():
        candidates.append(_Path(environ["HOME"]) / ".cache" / "sarship" / "numba")
    for path in candidates:
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError:
            continue
        if _os.access(path, _os.W_OK | _os.X_OK):
            return path
    import tempfile  # only here: the command line's start-up imports as little as it can

    uid = _os.getuid() if hasattr(_os, "getuid") else "user"
    path = _Path(tempfile.gettempdir()) / f"sarship-{uid}" / "numba"
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        pass  # Numba then falls back to its own locations
    return path


def _use_user_numba_cache() -> None:
    """Set ``NUMBA_CACHE_DIR`` to :func:`numba_cache_dir` unless the user set it, before Numba is
    imported by any sarship module (and re-read Numba's configuration where it already was).
    Dask worker processes, ``sarship serve``'s children and the tests import this package first."""
    if _os.environ.get("NUMBA_CACHE_DIR", "").strip():
        return
    _os.environ["NUMBA_CACHE_DIR"] = str(numba_cache_dir())
    if "numba.core.config" in _sys.modules:  # numba read its settings before sarship was imported
        _sys.modules["numba.core.config"].reload_config()


_use_user_numba_cache()

_checkout = _Path(__file__).resolve().parent.parent
if (_checkout / "pyproject.toml").is_file() and (_checkout / "pipeline" / "__init__.py").is_file():
    # Imported from a source checkout (``python -m sarship`` or ``python -m pytest`` in the
    # repository folder, which puts that folder first on sys.path): its top-level folders are
    # the subpackages, as the editable install maps them, so a checkout never mixes with an
    # installed copy of another version. An installed sarship has no pyproject.toml beside it.
    __path__.append(str(_checkout))  # noqa: F821 (a package's __path__)

from sarship.pipeline import __version__  # noqa: E402

__all__ = ["__version__"]
