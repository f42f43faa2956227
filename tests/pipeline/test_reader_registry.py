"""pipeline.readers.registry: one registry of readers, the entry point dispatches on it, in the
documented order; a reader registered for a test suffix is used by ``ingest`` and gone after."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import tifffile
from PIL import Image

from sarship.pipeline.errors import InputError
from sarship.pipeline.readers import (
    READERS,
    BaseReader,
    InputLimits,
    Probe,
    Reader,
    Source,
    choose,
    ingest,
    register,
    registered,
    unregister,
)
from sarship.pipeline.readers.entry import _open_source
from sarship.pipeline.scene import open_scene

REPO = Path(__file__).resolve().parents[2]
ORDER = ["safe", "polsarpro", "zarr", "tiff", "image", "npy"]


class _ArraySource(Source):
    """A test source: an array held in memory."""

    data: np.ndarray | None = None

    def _read(self, r0, r1, c0, c1):
        return self.data[r0:r1, c0:c1, None]


class SquaresReader(BaseReader):
    """A text format for the test: ``.sqr`` files of whitespace-separated rows of numbers."""

    name = "squares"

    def detect(self, probe: Probe) -> bool:
        return not probe.is_dir and probe.path.suffix == ".sqr"

    def open(self, path, limits, *, sidecar_root=None, swath=None):
        a = np.loadtxt(path, dtype=np.float32, ndmin=2)
        limits.check_pixels(path, *a.shape)  # before any pixel is handed on
        src = _ArraySource(path=path, shape=a.shape, nbands=1, dtype=a.dtype, fmt=self.name)
        src.data = a
        return src


def _inputs(tmp: Path) -> dict[str, Path]:
    """One small input of every registered format."""
    a = np.arange(12, dtype=np.uint8).reshape(3, 4)
    out = {"tiff": tmp / "a.tif", "image": tmp / "a.png", "npy": tmp / "a.npy"}
    tifffile.imwrite(out["tiff"], a)
    Image.fromarray(a).save(out["image"])
    np.save(out["npy"], a.astype(np.float32))
    (tmp / "a.jpg").write_bytes(b"\xff\xd8\xff\xe0" + b"\x00" * 12)
    out["jpeg"] = tmp / "a.jpg"
    safe = tmp / "S1A_X.SAFE"
    safe.mkdir()
    (safe / "manifest.safe").write_text("<xml/>")
    out["safe"] = safe
    pol = tmp / "C3"
    pol.mkdir()
    (pol / "C11.bin").write_bytes(b"\x00" * 4)
    out["polsarpro"] = pol
    z = tmp / "s.zarr"
    z.mkdir()
    (z / "zarr.json").write_text(json.dumps({"zarr_format": 3, "node_type": "group"}))
    out["zarr"] = z
    return out


def test_registry_holds_every_format_in_the_documented_order():
    assert [r.name for r in READERS] == ORDER
    assert all(isinstance(r, Reader) for r in READERS)
    doc = (REPO / "docs" / "adding-a-reader.md").read_text()
    assert " -> ".join(f"`{n}`" for n in ORDER) in doc  # the order the guide states is the registry's


def test_every_format_is_chosen_by_its_reader(tmp_path):
    paths = _inputs(tmp_path)
    chosen = {fmt: choose(p).name for fmt, p in paths.items()}
    assert chosen == {**{n: n for n in ORDER}, "jpeg": "image"}


def test_dispatch_order_decides_between_readers(tmp_path):
    paths = _inputs(tmp_path)
    # a Zarr scene holding C11.bin is the Zarr reader's, a SAFE folder holding one the SAFE reader's
    (paths["zarr"] / "C11.bin").write_bytes(b"\x00" * 4)
    (paths["safe"] / "zarr.json").write_text("{}")
    assert choose(paths["zarr"]).name == "zarr"
    assert choose(paths["safe"]).name == "safe"
    # the refusal of inputs that must stand alone follows the same order, whatever the inputs' order
    with pytest.raises(InputError, match="a PolSARpro folder cannot be combined"):
        ingest([paths["zarr"], paths["polsarpro"]], tmp_path / "out.zarr")
    with pytest.raises(InputError, match="a Zarr scene cannot be combined"):
        ingest([paths["npy"], paths["zarr"]], tmp_path / "out.zarr")


def test_a_registered_reader_is_used_by_ingest_and_gone_after(tmp_path):
    p = tmp_path / "a.sqr"
    p.write_text("1 2 3\n4 5 6\n")
    with pytest.raises(InputError, match="unrecognised format"):
        choose(p)
    with registered(SquaresReader()) as reader:
        assert READERS[-1] is reader and choose(p) is reader
        sc = ingest([p], tmp_path / "out.zarr", kind="intensity", looks=1)
        assert sc.attrs["source"] == ["a.sqr"]
        np.testing.assert_array_equal(
            np.asarray(open_scene(tmp_path / "out.zarr").array("intensity")[...]), [[1, 2, 3], [4, 5, 6]]
        )
        with pytest.raises(InputError, match="above the limit of 4"):  # the limits reach the reader
            _open_source(p, limits=InputLimits(max_pixels=4))
        with pytest.raises(InputError, match="--swath applies to Sentinel-1 SLC products only"):
            _open_source(p, swath="IW1")
    assert [r.name for r in READERS] == ORDER
    with pytest.raises(InputError, match="unrecognised format"):
        choose(p)


def test_register_before_takes_precedence_and_names_are_unique(tmp_path):
    paths = _inputs(tmp_path)
    npy_reader = type(
        "NpyFirst", (SquaresReader,), {"name": "npy-first", "detect": lambda self, probe: probe.path.suffix == ".npy"}
    )()
    with registered(npy_reader, before="safe"):
        assert READERS[0] is npy_reader and choose(paths["npy"]) is npy_reader
    assert choose(paths["npy"]).name == "npy"
    with pytest.raises(ValueError, match="registered already"):
        register(type("Dup", (SquaresReader,), {"name": "tiff"})())
    with pytest.raises(ValueError, match="no reader named 'nope'"):
        register(SquaresReader(), before="nope")
    with pytest.raises(KeyError):
        unregister("nope")
    assert [r.name for r in READERS] == ORDER


def test_a_failing_reader_is_named_in_one_line(tmp_path):
    class Broken(SquaresReader):
        name = "broken"

        def open(self, path, limits, *, sidecar_root=None, swath=None):
            raise RuntimeError("bad\nheader")

    p = tmp_path / "a.sqr"
    p.write_text("1\n")
    with registered(Broken()):
        with pytest.raises(InputError, match=r"^'.*a\.sqr': cannot read as BROKEN \(RuntimeError: bad header\)$"):
            _open_source(p)
