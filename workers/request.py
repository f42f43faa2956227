"""One detection job request, validated once for every way a job arrives.

``sarship detect`` (the command line), ``POST /processes/{id}/execution`` (the REST API),
the scheduled ingest's detector list and the service's job runner all describe a job the
same way: a scene, a detector, where its tiles run (``device``), optionally which scene
variable it reads (``channel``), and the detector's parameters. :class:`JobRequest` is that
envelope; :meth:`JobRequest.from_inputs` builds it from a flat mapping (the REST ``inputs``
object, the ``--set`` pairs plus the command line's own options, a stored job) and turns every
problem into one :class:`~sarship.pipeline.errors.InputError` line naming the input.

The detector's parameters are checked against its own pydantic model
(:attr:`~sarship.pipeline.detectors.base.DetectorSpec.params`) by :func:`parse_params`.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any, Literal, get_args

from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, ValidationError

from sarship.pipeline import detectors
from sarship.pipeline.detectors.base import DetectorParams, DetectorSpec
from sarship.pipeline.errors import InputError

#: Where a job's tiles run: ``auto`` (GPU workers when the cluster has any and the detector
#: has GPU code, else CPU workers), ``gpu`` or ``cpu`` (forced).
Device = Literal["auto", "cpu", "gpu"]
DEVICES: tuple[str, ...] = get_args(Device)
#: ``channel``: a scene variable name, or a comma list of them (a polarimetric detector's
#: channels, e.g. ``hh,vv``); no path separator, so never a path (``../../s1.zarr/intensity``).
CHANNEL = re.compile(r"\s*[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}\s*(,\s*[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}\s*){0,3}")
#: Inputs of a job that are not detector parameters.
RESERVED = ("scene", "device", "channel", "ais")
#: The most AIS files one job may name (``ais``: docs/ais.md).
MAX_AIS_FILES = 1000
#: The detector name that has the clutter-model fit choose among ``AUTO_CANDIDATES``
#: (pipeline/stats/model_fit.py; workers/jobs.py runs it); its parameters must suit every candidate.
AUTO = "auto"


def format_validation(exc: ValidationError, detector: str) -> str:
    """One line for the errors of a detector's parameter model."""
    msgs = []
    for e in exc.errors():
        loc = ".".join(str(x) for x in e.get("loc", ()))
        msg = e.get("msg", "invalid").removeprefix("Value error, ")
        ctx = e.get("ctx") or {}
        bounds = {
            "greater_than": "greater than",
            "greater_than_equal": "at least",
            "less_than": "less than",
            "less_than_equal": "at most",
        }
        if e.get("type") in bounds:  # the limit as a number reads (pydantic writes 1e-15 as 0.000000000000001)
            limit = next(iter(ctx.values()), None)
            if isinstance(limit, (int, float)):
                msg = f"must be {bounds[e['type']]} {limit:g}"
        if e.get("type") == "extra_forbidden":
            msgs.append(f"unknown parameter '{loc}' for detector '{detector}'")
        elif loc:
            msgs.append(f"parameter '{loc}': {msg} (got {e.get('input')!r})")
        else:
            msgs.append(msg)
    return "; ".join(msgs)


def parse_params(spec: DetectorSpec, settings: Mapping[str, Any]) -> DetectorParams:
    """``settings`` validated by the detector's parameter model; ``"none"``/``"null"``/``""``
    (as the command line's ``--set key=none`` writes them) mean unset. :class:`InputError`
    with one line naming every bad parameter otherwise."""
    clean = {}
    for k, v in settings.items():
        if isinstance(v, str) and v.lower() in ("none", "null", ""):
            v = None
        clean[k] = v
    try:
        return spec.params(**clean)
    except ValidationError as exc:
        raise InputError(format_validation(exc, spec.name)) from None


def _specs(detector: str) -> list[DetectorSpec]:
    """The detector's spec; for ``auto``, the candidates' (pipeline/stats/model_fit.py)."""
    if detector == AUTO:
        from sarship.pipeline.stats.model_fit import AUTO_CANDIDATES

        return [detectors.get(n) for n in AUTO_CANDIDATES]
    return [detectors.get(detector)]


def _ais_paths(value: Any) -> tuple[str, ...]:
    """The ``ais`` input: one path or a list of paths (at most :data:`MAX_AIS_FILES`)."""
    if value is None:
        return ()
    items = [value] if isinstance(value, str) else value
    if not isinstance(items, list) or not all(isinstance(v, str) and v.strip() for v in items):
        raise InputError(f"input 'ais' must be a path or a list of paths to AIS files, got {value!r}")
    if len(items) > MAX_AIS_FILES:
        raise InputError(f"input 'ais' names {len(items)} files, more than the {MAX_AIS_FILES} a job may read")
    return tuple(items)


class JobRequest(BaseModel):
    """A detection job: scene, detector, device, channel and the detector's parameters.

    Build it with :meth:`from_inputs` (one-line :class:`InputError` on any problem); the
    parsed detector parameters are :meth:`detector_params`, parsed once per request and kept
    (a copy that changes ``detector`` or ``params`` parses again, see :meth:`model_copy`).
    :meth:`from_stored` rebuilds a request the service validated when the job was posted and
    stored as :meth:`inputs`, without validating it again. ``scene`` is kept as given: the
    command line opens it as a path, the service resolves it within its allowed folders.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    scene: str = Field(min_length=1, description="scene store path, or scene id (service)")
    detector: str = Field(description="detector name (sarship detectors)")
    device: Device = Field("auto", description="where tiles run: auto, gpu or cpu")
    channel: str | None = Field(None, min_length=1, description="scene variable the detector reads")
    params: dict[str, Any] = Field(default_factory=dict, description="the detector's parameters")
    ais: tuple[str, ...] = Field((), description="AIS files matched to the detections (docs/ais.md)")
    #: the parsed detector parameters (:meth:`detector_params`), once parsed
    _parsed: DetectorParams | None = PrivateAttr(default=None)

    @classmethod
    def from_inputs(cls, detector: str, inputs: Mapping[str, Any]) -> JobRequest:
        """The request of ``detector`` with the flat ``inputs`` (``scene``, ``device``,
        ``channel`` and parameters), validated: unknown detector, missing scene, bad device or
        channel, parameter values that are not numbers or strings, and every parameter the
        detector's model refuses, each named in one line (:class:`InputError`)."""
        if not isinstance(detector, str) or (detector not in detectors.names() and detector != AUTO):
            raise InputError(f"unknown detector '{detector}' (known: {', '.join(detectors.names())}; or {AUTO})")
        if not isinstance(inputs, Mapping):
            raise InputError("inputs must be an object (scene, device, channel and parameters)")
        scene = inputs.get("scene")
        if scene is None:
            raise InputError("input 'scene' is required (a scene id or a path)")
        if not isinstance(scene, str) or not scene.strip():
            raise InputError(f"input 'scene' must be a scene id or a path, got {scene!r}")
        device = inputs.get("device", "auto")
        if device not in DEVICES:
            raise InputError(f"input 'device' must be {', '.join(DEVICES[:-1])} or {DEVICES[-1]}, got {device!r}")
        channel = inputs.get("channel")
        if channel is not None and (not isinstance(channel, str) or not CHANNEL.fullmatch(channel)):
            raise InputError(
                f"input 'channel' must be a scene variable name (or a comma list of them, "
                f"e.g. hh,vv), never a path: got {channel!r}"
            )
        ais = _ais_paths(inputs.get("ais"))
        params = {k: v for k, v in inputs.items() if k not in RESERVED}
        fields = {k: f for s in _specs(detector) for k, f in s.params.model_fields.items()}
        for k, v in params.items():
            if isinstance(v, bool) and k in fields and fields[k].annotation is bool:
                continue  # a true/false parameter (e.g. sidelobes): JSON booleans as its schema says
            if isinstance(v, (bool, dict, list)) or not isinstance(v, (int, float, str, type(None))):
                raise InputError(f"parameter '{k}' must be a number or a string, got {v!r}")
        req = cls(scene=scene, detector=detector, device=device, channel=channel, params=params, ais=ais)
        req.detector_params()  # every parameter checked now, not when a tile runs
        return req

    @classmethod
    def from_stored(cls, detector: str, inputs: Mapping[str, Any]) -> JobRequest:
        """The request a job store keeps (the flat :meth:`inputs` of a request that
        :meth:`from_inputs` validated when the job was submitted), rebuilt without validating
        it again: its parameters are parsed once, when the run first asks for them
        (:meth:`detector_params`)."""
        return cls.model_construct(
            scene=inputs.get("scene", ""),
            detector=detector,
            device=inputs.get("device", "auto"),
            channel=inputs.get("channel"),
            params={k: v for k, v in inputs.items() if k not in RESERVED},
            ais=tuple(inputs.get("ais") or ()),
        )

    def model_copy(self, *, update: Mapping[str, Any] | None = None, deep: bool = False) -> JobRequest:
        """A copy with ``update``; the parsed parameters are kept unless ``detector`` or
        ``params`` change (then the copy parses its own)."""
        copy = super().model_copy(update=update, deep=deep)
        if update and ("detector" in update or "params" in update):
            copy._parsed = None
        return copy

    def with_param(self, name: str, value: Any) -> JobRequest:
        """A copy with detector parameter ``name`` set to ``value`` (already valid for it, e.g.
        the service's rasterised ``land_mask`` FILE): the parsed parameters are updated
        rather than parsed again."""
        copy = self.model_copy(update={"params": {**self.params, name: value}})
        if self._parsed is not None:
            copy._parsed = self._parsed.model_copy(update={name: value})
        return copy

    @property
    def spec(self) -> DetectorSpec:
        return detectors.get(self.detector)

    def detector_params(self) -> DetectorParams:
        """The detector's parameters, parsed by its model (:func:`parse_params`) the first time
        they are asked for and kept; for ``auto``, checked against every candidate's model and
        those of the first returned."""
        if self._parsed is None:
            self._parsed = self._parse_params()
        return self._parsed

    def _parse_params(self) -> DetectorParams:
        if self.detector == AUTO:
            parsed = []
            for spec in _specs(AUTO):
                try:
                    parsed.append(parse_params(spec, self.params))
                except InputError as exc:
                    raise InputError(
                        f"detector auto (candidates {', '.join(s.name for s in _specs(AUTO))}): {exc}"
                    ) from None
            return parsed[0]
        return parse_params(self.spec, self.params)

    def inputs(self) -> dict[str, Any]:
        """The flat inputs (the inverse of :meth:`from_inputs`): what a job store keeps."""
        out: dict[str, Any] = {"scene": self.scene, "device": self.device}
        if self.channel is not None:
            out["channel"] = self.channel
        if self.ais:
            out["ais"] = list(self.ais)
        return {**out, **self.params}
