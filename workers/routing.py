"""Which workers run a detector's tiles: GPU workers, CPU workers, or any.

Tile tasks are submitted with ``client.map`` (futures, not a collection graph), so their
restrictions are never lost to graph fusion: each tile future carries ``resources={"GPU":
1}`` or ``{"CPU": 1}`` explicitly, or a ``workers=[...]`` list when some eligible workers
advertise no resources at all (plain ``dask worker`` processes, which a resource
restriction would never match).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from sarship.pipeline.errors import InputError
from sarship.workers.request import DEVICES


@dataclass(frozen=True)
class Placement:
    device: str  # what the tiles run on: "gpu" or "cpu"
    submit: dict = field(default_factory=dict)  # extra keyword arguments of client.map
    reason: str = ""


def plan(requested: str, detector: str, has_gpu: bool, workers: dict[str, dict]) -> Placement:
    """Placement of the tiles of ``detector`` for ``--device requested`` on ``workers``.

    ``workers``: the scheduler's ``{address: {"resources": {...}, ...}}``.

    * ``gpu``: GPU workers only; an error when the detector has no GPU code or the cluster
      no GPU worker.
    * ``cpu``: CPU workers (``CPU`` resource, or none advertised); GPU-only clusters run the
      CPU code on their GPU workers' processes.
    * ``auto``: ``gpu`` when the detector has GPU code and a GPU worker exists, else ``cpu``.
    """
    if requested not in DEVICES:
        raise InputError(f"--device must be {', '.join(DEVICES[:-1])} or {DEVICES[-1]}, got '{requested}'")
    gpu = [a for a, w in workers.items() if float((w.get("resources") or {}).get("GPU", 0)) > 0]
    cpu_res = [a for a, w in workers.items() if float((w.get("resources") or {}).get("CPU", 0)) > 0]
    plain = [a for a, w in workers.items() if not (w.get("resources") or {})]
    if requested == "gpu":
        if not has_gpu:
            raise InputError(f"--device gpu: detector '{detector}' has no GPU implementation in this version")
        if not gpu:
            raise InputError(
                "--device gpu: no GPU worker on the cluster (start them with 'sarship worker "
                "--gpus all', or use --device auto/cpu)"
            )
        return Placement("gpu", {"resources": {"GPU": 1}}, f"{len(gpu)} GPU workers")
    if requested == "auto" and has_gpu and gpu:
        return Placement("gpu", {"resources": {"GPU": 1}}, f"auto: {len(gpu)} GPU workers")
    why = "auto: " if requested == "auto" else ""
    if requested == "auto" and gpu and not has_gpu:
        why += f"'{detector}' has no GPU code; "
    if cpu_res and not plain:
        return Placement("cpu", {"resources": {"CPU": 1}}, why + f"{len(cpu_res)} CPU workers")
    if cpu_res or plain:
        if not gpu:  # nothing to keep away from: no restriction
            return Placement("cpu", {}, why + f"{len(cpu_res) + len(plain)} workers")
        return Placement(
            "cpu",
            {"workers": sorted(cpu_res + plain), "allow_other_workers": False},
            why + f"{len(cpu_res) + len(plain)} CPU workers",
        )
    return Placement("cpu", {}, why + "no CPU workers: the GPU workers run the CPU code")
