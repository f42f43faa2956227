"""Every ``SARSHIP_*`` environment variable read below the service, declared once.

Each variable is one :class:`Var`: its type, default, bounds, one-line meaning, the modules that
read it, how its text is parsed and the one line a bad value gets. Code reads a variable with
:func:`read` at the moment it needs it (the environment of that moment: tests and the command
line set variables per process), never with ``os.environ`` (``tests/project/test_settings_vars.py``
parses every module to hold that).

The same definitions make the typed pydantic-settings model :func:`model` (``SARSHIP_``
prefix), from which the service's :class:`sarship.service.settings.Settings` takes the variables
it shares with the layers below (:func:`field`: ``SARSHIP_SCHEDULER``, ``SARSHIP_LAND_MAX_MB``),
and from which ``docs/interfaces/settings.md`` lists them (``python -m sarship.docs_settings``).

This module imports only the standard library: :func:`read` runs in the command's end of the
warm cluster (:mod:`sarship.warm`), which must start without pydantic; pydantic is imported
only when :func:`model` is first called.
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal, NamedTuple

from sarship.pipeline.errors import InputError

#: The prefix of every variable.
PREFIX = "SARSHIP_"
#: Values that turn ``SARSHIP_WARM`` off (case-insensitive).
OFF = ("0", "false", "no", "off")
#: ``SARSHIP_READER``'s values.
READERS = ("tensorstore", "zarr")
#: ``SARSHIP_WORKER_START``'s values.
START_METHODS = ("fork", "forkserver", "spawn")
#: ``SARSHIP_GPU_HSUM``'s values.
HSUM_METHODS = ("direct", "transpose")


class Var(NamedTuple):
    """One ``SARSHIP_*`` variable (a named tuple, not a dataclass: ``dataclasses`` costs the
    warm cluster's client ~10 ms of imports).

    Attributes
    ----------
    name : str
        The field name (``land_max_mb`` for ``SARSHIP_LAND_MAX_MB``).
    type : Any
        The annotation of its value in :func:`model`.
    default : Any
        Its value when unset (or blank, unless ``blank_is_unset`` is False).
    meaning : str
        One line: what it sets (the model field's description).
    readers : tuple of str
        The modules that read it (the docs table's last column).
    parse : callable
        Text (after ``text``) -> value; ``ValueError`` for a bad value.
    bad : str
        The message of a bad value, ``{value}`` the text (after ``text``).
    text : {"strip", "lower", "raw"}
        The text parsed: stripped, stripped and lower-cased, or as set.
    blank_is_unset : bool
        Whether a blank value means the default (else it is parsed like any other).
    bounds : dict, optional
        Constraints of the model field (``gt``, ``ge``, ``allow_inf_nan``...).
    default_text : str, optional
        The default as the docs state it, where the code computes it.
    typed_by_model : bool
        The model field checks a value by its type and bounds alone (pydantic's own messages:
        a variable the service shares, whose start-up errors are pydantic's); else the model
        applies ``text`` and ``parse`` too, so the model and :func:`read` give the same value.
    """

    name: str
    type: Any
    default: Any
    meaning: str
    readers: tuple[str, ...]
    parse: Callable[[str], Any]
    bad: str
    text: Literal["strip", "lower", "raw"] = "strip"
    blank_is_unset: bool = True
    bounds: dict[str, Any] | None = None
    default_text: str | None = None
    typed_by_model: bool = False

    @property
    def env(self) -> str:
        """The environment variable: ``SARSHIP_`` and the name in capitals."""
        return PREFIX + self.name.upper()


# ----------------------------------------------------------------------------- text rules


def _one_of(choices: tuple[str, ...]) -> Callable[[str], str]:
    def parse(text: str) -> str:
        if text not in choices:
            raise ValueError(text)
        return text

    return parse


def _whole_at_least_one(text: str) -> int:
    if not text.isdigit() or int(text) < 1:
        raise ValueError(text)
    return int(text)


def _positive_finite(text: str) -> float:
    value = float(text)
    if not (value > 0 and math.isfinite(value)):
        raise ValueError(text)
    return value


def _non_negative_finite(text: str) -> float:
    value = float(text)
    if not (math.isfinite(value) and value >= 0):
        raise ValueError(text)
    return value


def _pixels(text: str) -> int:
    value = int(float(text))
    if value < 0:
        raise ValueError(text)
    return value


def _host(text: str) -> str:
    """An IP address (brackets dropped) or a well-formed host name."""
    import ipaddress

    h = text.strip("[]")
    try:
        ipaddress.ip_address(h)
        return h
    except ValueError:
        pass
    if all(part and len(part) <= 63 and part.replace("-", "").isalnum() for part in h.split(".")) and len(h) <= 253:
        return h
    raise ValueError(text)


def _at_least_one(text: str) -> int:
    return max(1, int(text))


def _text(text: str) -> str:
    return text


def _not_zero(text: str) -> bool:
    return text != "0"


def _not_off(text: str) -> bool:
    return text not in OFF


def _not_blank(text: str) -> bool:
    return text != ""


# ----------------------------------------------------------------------------- the variables

_CLUSTER = "sarship.workers.cluster"
VARIABLES: dict[str, Var] = {
    v.name: v
    for v in (
        Var(
            "reader",
            Literal[READERS] | None,
            None,  # type: ignore[valid-type]
            "library that reads scene arrays: tensorstore or zarr (zarr-python)",
            ("sarship.pipeline.tiling.inputs",),
            _one_of(READERS),
            f"SARSHIP_READER must be one of {', '.join(READERS)}, got '{{value}}'",
            text="lower",
            default_text="tensorstore when installed, else zarr",
        ),
        Var(
            "ingest_writers",
            int | None,
            None,
            "tile writes an ingest keeps going at once",
            ("sarship.pipeline.readers.writing",),
            _whole_at_least_one,
            "SARSHIP_INGEST_WRITERS must be a whole number >= 1, got '{value}'",
            bounds={"ge": 1},
            default_text="the cores, at most 8 (1 in the service's ingest process)",
        ),
        Var(
            "land_max_mb",
            float,
            64.0,
            "largest GeoJSON land_mask FILE, MiB (the command line reads the same SARSHIP_LAND_MAX_MB); a larger one "
            "is refused when the job is submitted",
            ("sarship.pipeline.land.landmask_files", "sarship.service.settings"),
            _positive_finite,
            "SARSHIP_LAND_MAX_MB must be a positive number of MiB, got '{value}'",
            bounds={"gt": 0.0, "allow_inf_nan": False},
            typed_by_model=True,
        ),
        Var(
            "gpu_hsum",
            Literal[HSUM_METHODS],
            "transpose",  # type: ignore[valid-type]
            "horizontal pass of the GPU box sums: direct or transpose (read when the module is imported)",
            ("sarship.pipeline.gpu.box",),
            _one_of(HSUM_METHODS),
            f"SARSHIP_GPU_HSUM must be one of {', '.join(HSUM_METHODS)}, got '{{value}}'",
            text="raw",
        ),
        Var(
            "gpu_pool_fraction",
            float,
            0.8,
            "fraction of the device memory the CuPy pool may hold (kept in 0.05-1)",
            ("sarship.pipeline.gpu",),
            float,
            "SARSHIP_GPU_POOL_FRACTION must be a number, got '{value}'",
            text="raw",
            blank_is_unset=False,
        ),
        Var(
            "threads_max_px",
            int,
            8192 * 8192,
            "sarship detect without --scheduler runs scenes up to this many pixels on in-process threads "
            "(0: always worker processes)",
            (_CLUSTER,),
            _pixels,
            "SARSHIP_THREADS_MAX_PX must be a whole number of pixels >= 0, got '{value}'",
            bounds={"ge": 0},
        ),
        Var(
            "cluster_host",
            str,
            "127.0.0.1",
            "interface a local cluster's scheduler, nannies and workers listen on (an IP address or host name of "
            "this machine)",
            (_CLUSTER,),
            _host,
            "SARSHIP_CLUSTER_HOST must be an IP address or host name of this machine, got '{value}'",
        ),
        Var(
            "worker_start",
            Literal[START_METHODS] | None,
            None,  # type: ignore[valid-type]
            "how a local cluster starts its worker processes: fork, forkserver or spawn",
            (_CLUSTER,),
            _one_of(START_METHODS),
            f"SARSHIP_WORKER_START must be one of {', '.join(START_METHODS)}, got {{value!r}}",
            text="lower",
            default_text="fork for one command on Linux without CUDA, else spawn",
        ),
        Var(
            "gpu_procs",
            int | None,
            None,
            "worker processes per GPU of a local cluster (at least 1)",
            (_CLUSTER, "sarship.workers.worker"),
            _at_least_one,
            "SARSHIP_GPU_PROCS must be a whole number, got {value!r}",
            text="raw",
            blank_is_unset=False,
            default_text="a quarter of the cores per GPU, at most 4 in all",
        ),
        Var(
            "gpu_threads",
            int,
            2,
            "threads of each GPU worker process of a local cluster",
            (_CLUSTER,),
            int,
            "SARSHIP_GPU_THREADS must be a whole number, got {value!r}",
            text="raw",
            blank_is_unset=False,
        ),
        Var(
            "block_cache_mb",
            float | None,
            None,
            "decoded-block cache of each worker, MiB (0: keep none)",
            ("sarship.workers.blockcache",),
            _non_negative_finite,
            "SARSHIP_BLOCK_CACHE_MB must be a number of MiB >= 0, got '{value}'",
            bounds={"ge": 0.0, "allow_inf_nan": False},
            default_text="memory / (4 x cores), at most 2 GiB",
        ),
        Var(
            "device",
            str | None,
            None,
            "set by a local cluster in each worker process it starts: gpu or cpu",
            ("sarship.workers.gpus",),
            _text,
            "SARSHIP_DEVICE: bad value {value!r}",
            text="raw",
        ),
        Var(
            "cuda_warmup",
            bool,
            True,
            "GPU workers make their CUDA context while the land pass runs (0: off)",
            ("sarship.workers.gpus",),
            _not_zero,
            "SARSHIP_CUDA_WARMUP: bad value {value!r}",
            text="raw",
        ),
        Var(
            "scheduler",
            str | None,
            None,
            "Dask scheduler address (default: a local cluster)",
            ("sarship.cli", "sarship.warm", "sarship.service.settings"),
            _text,
            "SARSHIP_SCHEDULER: bad value {value!r}",
            typed_by_model=True,
        ),
        Var(
            "fast_exit",
            bool,
            True,
            "batch commands end with os._exit once their outputs are in place (0: normal exit)",
            ("sarship.cli",),
            _not_zero,
            "SARSHIP_FAST_EXIT: bad value {value!r}",
            text="raw",
        ),
        Var(
            "debug",
            bool,
            False,
            "print the traceback of an unexpected error (any non-empty value)",
            ("sarship.cli", "sarship.warm", "sarship.warm_process"),
            _not_blank,
            "SARSHIP_DEBUG: bad value {value!r}",
            text="raw",
        ),
        Var(
            "warm",
            bool,
            True,
            "sarship detect uses a running warm cluster (0, false, no, off: never)",
            ("sarship.warm",),
            _not_off,
            "SARSHIP_WARM: bad value {value!r}",
            text="lower",
        ),
        Var(
            "warm_socket",
            Path | None,
            None,
            "socket path of the warm cluster",
            ("sarship.warm",),
            Path,
            "SARSHIP_WARM_SOCKET: bad value {value!r}",
            default_text="$XDG_RUNTIME_DIR/sarship/warm.sock, else /tmp/sarship-UID/warm.sock",
        ),
    )
}


def raw(name: str) -> str | None:
    """The text of ``SARSHIP_<NAME>`` as set now, or None (for code that hands it on as it is).

    Parameters
    ----------
    name : str
        A key of :data:`VARIABLES`.

    Returns
    -------
    str or None
    """
    return os.environ.get(VARIABLES[name].env)


def read(name: str) -> Any:
    """The value of ``SARSHIP_<NAME>`` in the environment now, parsed by its :class:`Var`.

    Parameters
    ----------
    name : str
        A key of :data:`VARIABLES`.

    Returns
    -------
    Any
        The variable's default when it is unset (or blank, where blank means unset), else its
        parsed value.

    Raises
    ------
    InputError
        For a bad value: one line naming the variable and the problem.
    """
    return parse_text(VARIABLES[name], os.environ.get(VARIABLES[name].env))


def parse_text(var: Var, text: str | None) -> Any:
    """The value of ``var`` set to ``text`` (None: unset); see :func:`read`.

    Parameters
    ----------
    var : Var
    text : str or None

    Returns
    -------
    Any

    Raises
    ------
    InputError
        For a bad value.
    """
    if text is None:
        return var.default
    if var.text != "raw":
        text = text.strip()
        if var.text == "lower":
            text = text.lower()
    if var.blank_is_unset and not text:
        return var.default
    try:
        return var.parse(text)
    except ValueError:
        raise InputError(var.bad.format(value=text)) from None


@functools.cache
def model() -> type:
    """Every variable of :data:`VARIABLES` as one typed pydantic-settings model (``SARSHIP_``
    prefix): type, default, bounds and meaning.

    Returns
    -------
    type
        A subclass of ``pydantic_settings.BaseSettings``.
    """
    from typing import Annotated

    from pydantic import BeforeValidator, Field, create_model
    from pydantic_settings import BaseSettings, SettingsConfigDict

    class Environment(BaseSettings):
        """Every ``SARSHIP_*`` variable read below the service (:data:`VARIABLES`)."""

        model_config = SettingsConfigDict(env_prefix=PREFIX, extra="ignore")

    def rule(var: Var) -> Callable[[Any], Any]:
        def check(value: Any) -> Any:
            if not isinstance(value, str):
                return value
            try:
                return parse_text(var, value)
            except InputError as exc:
                raise ValueError(str(exc)) from None

        return check

    fields = {}
    for v in VARIABLES.values():
        annotation = v.type if v.typed_by_model else Annotated[v.type, BeforeValidator(rule(v))]
        fields[v.name] = (annotation, Field(v.default, description=v.meaning, **(v.bounds or {})))
    return create_model("Environment", __base__=Environment, __module__=__name__, **fields)


def field(name: str) -> Any:
    """The model's field of ``SARSHIP_<NAME>`` (a copy), for a settings class that shares it.

    Parameters
    ----------
    name : str
        A key of :data:`VARIABLES`.

    Returns
    -------
    pydantic.fields.FieldInfo
    """
    import copy

    return copy.copy(model().model_fields[name])
