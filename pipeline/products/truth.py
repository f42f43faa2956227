"""Ships from any truth source (and from ``detections.geojson``) in one form: :class:`Ship`.

Sources read by :func:`load_ships`:

GeoJSON (``.geojson`` / ``.json``)
    A FeatureCollection in the schema of docs/interfaces/files.md: per Feature, ``properties.bbox_px``
    ``[row0, col0, row1, col1]`` (half-open, scene pixels), ``properties.centroid_px``
    ``[row, col]`` (continuous coordinates; the box centre is used when it is absent) and an
    optional ``difficult`` (in ``properties``, or on the Feature itself). All other
    properties are kept in :attr:`Ship.properties`.

PASCAL-VOC xml (one file, or a folder of ``*.xml``: :func:`load_voc_folder`)
    ``<object><name>``, ``<difficult>`` (tag names are matched case-insensitively: the
    SAR-Ship-Dataset writes ``<Difficult>``), ``<bndbox><xmin><ymin><xmax><ymax>`` with
    x = column, y = row.

    **Coordinate base.** The classic VOC devkit uses 1-based *inclusive* pixel indices. The
    real SAR-Ship-Dataset files follow it: over the 68 boxes of the 12 chips (256 x 256) the
    smallest ``xmin``/``ymin`` is 1 and the largest ``xmax``/``ymax`` is 256 -- a 0-based
    inclusive box could not reach 256. So by default (``one_based=True``)::

        row0 = ymin - 1,  col0 = xmin - 1,  row1 = ymax,  col1 = xmax   (half-open, 0-based)

    With ``one_based=False`` the numbers are read as 0-based inclusive
    (``row0 = ymin, row1 = ymax + 1``). Boxes are clipped to ``[0, size]`` when the file
    gives ``<size>`` (a stray ``0`` in a 1-based file becomes ``-1`` and is clipped to 0).
    The centroid of a box truth is the box centre.

Mask images (PNG, TIFF, BMP, GIF, JPEG ...; also a 2-D ``.npy`` or a Zarr ``mask`` array)
    Ship pixels are the non-zero pixels of a grey mask (also an RGB image whose three
    channels are equal). For a colour mask, the HRSID convention: ship = (0, 255, 0); any
    *dominantly green* pixel counts (G >= 128 and G - max(R, B) >= 64), so lightly
    compressed or anti-aliased masks still work; a colour mask with no green pixel at all
    falls back to "any channel non-zero". Objects are the 8-connected components
    (:func:`scipy.ndimage.label`); bbox = ``[rmin, cmin, rmax + 1, cmax + 1]``, centroid =
    mean pixel index + 0.5 (continuous coordinates: pixel (r, c) spans [r, r+1) x [c, c+1)).
    Touching ships merge into one component (a known limit of mask truth).

Unreadable input of any kind raises :class:`sarship.pipeline.errors.InputError` with a one-line
message naming the file and the problem.
"""

from __future__ import annotations

import json
import math
import os
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sarship.pipeline.errors import InputError

GEOJSON_SUFFIXES = (".geojson", ".json")
VOC_SUFFIXES = (".xml",)
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".bmp", ".gif", ".jpg", ".jpeg", ".webp", ".pgm", ".ppm", ".pbm")

#: "Dominantly green" thresholds for colour (HRSID-style) masks.
GREEN_MIN = 128
GREEN_MARGIN = 64


@dataclass
class Ship:
    """One truth or detected object, in scene pixels.

    ``bbox`` is ``(row0, col0, row1, col1)`` half-open; ``centroid`` is ``(row, col)`` in
    continuous coordinates (pixel (r, c) spans [r, r+1) x [c, c+1), so its centre is
    (r + 0.5, c + 0.5)).
    """

    bbox: tuple[float, float, float, float]
    centroid: tuple[float, float]
    difficult: bool = False
    properties: dict = field(default_factory=dict)

    @classmethod
    def from_bbox(cls, bbox: Iterable[float], difficult: bool = False, **properties: Any) -> Ship:
        """A ship whose centroid is the centre of ``bbox``."""
        r0, c0, r1, c1 = (float(v) for v in bbox)
        return cls((r0, c0, r1, c1), ((r0 + r1) / 2.0, (c0 + c1) / 2.0), bool(difficult), dict(properties))

    @property
    def area(self) -> float:
        r0, c0, r1, c1 = self.bbox
        return max(0.0, r1 - r0) * max(0.0, c1 - c0)

    def to_feature(self) -> dict:
        """A GeoJSON Feature in the detections schema (docs/interfaces/files.md) (``geometry`` null: pixel coordinates only)."""
        props = {k: _jsonable(v) for k, v in self.properties.items()}
        props["bbox_px"] = [_num(v) for v in self.bbox]
        props["centroid_px"] = [float(v) for v in self.centroid]
        if self.difficult:
            props["difficult"] = True
        else:
            props.pop("difficult", None)
        return {"type": "Feature", "geometry": props.pop("geometry", None), "properties": props}


# ----------------------------------------------------------------------------- helpers


def _num(v: float) -> int | float:
    f = float(v)
    return int(f) if f.is_integer() else f


def _jsonable(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def _check_exists(path: Path) -> None:
    if not path.exists():
        raise InputError(f"'{path}': no such file or folder")


def _numbers(value: Any, n: int, what: str, where: str) -> tuple[float, ...]:
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise InputError(f"{where}: '{what}' must be a list of {n} numbers, got {value!r:.80}")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise InputError(f"{where}: '{what}' must be a list of {n} numbers, got {value!r:.80}")
        f = float(v)
        if not math.isfinite(f):
            raise InputError(f"{where}: '{what}' holds a non-finite number")
        out.append(f)
    return tuple(out)


def _check_box(box: tuple[float, ...], where: str) -> None:
    r0, c0, r1, c1 = box
    if r1 < r0 or c1 < c0:
        raise InputError(f"{where}: box {list(box)} has row1 < row0 or col1 < col0")


def _sniff(path: Path) -> str:
    """'geojson', 'voc', 'image', 'npy', 'zarr' or 'folder' from the suffix, else from content."""
    if path.is_dir():
        if path.suffix.lower() == ".zarr" or (path / "zarr.json").exists():
            return "zarr"
        return "folder"
    suf = path.suffix.lower()
    if suf in GEOJSON_SUFFIXES:
        return "geojson"
    if suf in VOC_SUFFIXES:
        return "voc"
    if suf in IMAGE_SUFFIXES:
        return "image"
    if suf == ".npy":
        return "npy"
    try:
        with open(path, "rb") as fh:
            head = fh.read(512).lstrip()
    except OSError as exc:
        raise InputError(f"'{path}': cannot read ({exc.strerror or exc})") from None
    if head.startswith(b"\xef\xbb\xbf"):
        head = head[3:].lstrip()
    if head.startswith(b"{"):
        return "geojson"
    if head.startswith(b"<"):
        return "voc"
    if head.startswith(b"\x93NUMPY"):
        return "npy"
    return "image"


# ----------------------------------------------------------------------------- GeoJSON


def _read_json(path: Path) -> Any:
    try:
        with open(path, "rb") as fh:
            return json.loads(fh.read().decode("utf-8-sig"))
    except OSError as exc:
        raise InputError(f"'{path}': cannot read ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise InputError(f"'{path}': not a GeoJSON file (not UTF-8 text)") from None
    except json.JSONDecodeError as exc:
        raise InputError(f"'{path}': not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})") from None


def _feature_collection(path: Path) -> list[dict]:
    doc = _read_json(path)
    if not isinstance(doc, dict) or doc.get("type") != "FeatureCollection":
        raise InputError(f"'{path}': not a GeoJSON FeatureCollection")
    feats = doc.get("features")
    if not isinstance(feats, list):
        raise InputError(f"'{path}': FeatureCollection has no 'features' list")
    return feats


def _ship_from_feature(feat: Any, where: str) -> Ship:
    if not isinstance(feat, dict) or feat.get("type") != "Feature":
        raise InputError(f"{where}: not a GeoJSON Feature")
    props = feat.get("properties")
    if not isinstance(props, dict):
        raise InputError(f"{where}: Feature has no 'properties' object")
    if "bbox_px" not in props:
        raise InputError(f"{where}: Feature properties lack 'bbox_px'")
    box = _numbers(props["bbox_px"], 4, "bbox_px", where)
    _check_box(box, where)
    if props.get("centroid_px") is not None:
        cen = _numbers(props["centroid_px"], 2, "centroid_px", where)
    else:
        cen = ((box[0] + box[2]) / 2.0, (box[1] + box[3]) / 2.0)
    difficult = props.get("difficult", feat.get("difficult", False))
    if difficult is None:
        difficult = False
    if not isinstance(difficult, (bool, int)):
        raise InputError(f"{where}: 'difficult' must be true or false, got {difficult!r:.40}")
    extra = {k: v for k, v in props.items() if k not in ("bbox_px", "centroid_px", "difficult")}
    if feat.get("geometry") is not None:
        extra["geometry"] = feat["geometry"]
    return Ship(box, cen, bool(difficult), extra)


def load_geojson(path: str | os.PathLike) -> list[Ship]:
    """Ships of a FeatureCollection in the detections schema (truth or detections)."""
    p = Path(path)
    _check_exists(p)
    feats = _feature_collection(p)
    return [_ship_from_feature(f, f"'{p}' feature {i}") for i, f in enumerate(feats)]


def load_detections(path: str | os.PathLike) -> list[Ship]:
    """Detections of a ``detections.geojson`` (docs/interfaces/files.md)."""
    p = Path(path)
    _check_exists(p)
    if p.is_dir():
        raise InputError(f"'{p}': is a folder, expected a detections GeoJSON file")
    return load_geojson(p)


def detections_scene(path: str | os.PathLike) -> str | None:
    """The scene name (stem, e.g. ``Gao_ship_hh_0201611139301040015``) a detections file is about.

    Looked up in the FeatureCollection (``scene``, ``properties.scene``), then in a
    ``run.json`` beside it (``scene``, ``inputs.scene``); a path-like value gives its last
    component without ``.zarr`` / image suffixes. ``None`` when nothing names the scene.
    """
    p = Path(path)
    candidates: list[Any] = []
    try:
        doc = json.loads(p.read_bytes().decode("utf-8-sig"))
    except Exception:
        doc = None
    if isinstance(doc, dict):
        candidates.append(doc.get("scene"))
        if isinstance(doc.get("properties"), dict):
            candidates.append(doc["properties"].get("scene"))
    run = p.parent / "run.json"
    if run.is_file():
        try:
            rdoc = json.loads(run.read_text(encoding="utf-8-sig"))
        except Exception:
            rdoc = None
        if isinstance(rdoc, dict):
            candidates.append(rdoc.get("scene"))
            if isinstance(rdoc.get("inputs"), dict):
                candidates.append(rdoc["inputs"].get("scene"))
    for c in candidates:
        if isinstance(c, dict):
            c = c.get("name") or c.get("path")
        if isinstance(c, str) and c.strip():
            return _scene_stem(c.strip())
    return None


def _scene_stem(name: str) -> str:
    base = name.rstrip("/\\").replace("\\", "/").rsplit("/", 1)[-1]
    while True:
        stem, dot, suf = base.rpartition(".")
        if dot and ("." + suf.lower()) in (".zarr", ".xml", ".geojson", ".json", ".npy") + IMAGE_SUFFIXES:
            base = stem
        else:
            return base


def ships_to_geojson(ships: Iterable[Ship], **members: Any) -> dict:
    """A FeatureCollection of ``ships`` (extra top-level ``members``, e.g. ``scene=...``)."""
    doc: dict[str, Any] = {"type": "FeatureCollection"}
    doc.update(members)
    doc["features"] = [s.to_feature() for s in ships]
    return doc


def write_geojson(path: str | os.PathLike, ships: Iterable[Ship], **members: Any) -> None:
    """Write ``ships`` as a FeatureCollection in the detections schema (atomically: temp file + rename)."""
    p = Path(path)
    tmp = p.with_name(f".{p.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(ships_to_geojson(ships, **members), allow_nan=False), encoding="utf-8")
    os.replace(tmp, p)


# ----------------------------------------------------------------------------- PASCAL-VOC


def _child(elem: ET.Element, tag: str) -> ET.Element | None:
    tag = tag.lower()
    for c in elem:
        if isinstance(c.tag, str) and c.tag.lower() == tag:
            return c
    return None


def _text(elem: ET.Element, tag: str) -> str | None:
    c = _child(elem, tag)
    if c is None or c.text is None:
        return None
    return c.text.strip()


def load_voc(path: str | os.PathLike, one_based: bool = True) -> list[Ship]:
    """Ships of one PASCAL-VOC xml (see the module docstring for the coordinate base)."""
    p = Path(path)
    _check_exists(p)
    try:
        root = ET.parse(p).getroot()
    except ET.ParseError as exc:
        raise InputError(f"'{p}': not valid XML ({exc})") from None
    except OSError as exc:
        raise InputError(f"'{p}': cannot read ({exc.strerror or exc})") from None
    if not isinstance(root.tag, str) or root.tag.lower() != "annotation":
        raise InputError(f"'{p}': not a PASCAL-VOC annotation (root element <{root.tag}>)")
    height = width = None
    size = _child(root, "size")
    if size is not None:
        try:
            w, h = _text(size, "width"), _text(size, "height")
            width = float(w) if w else None
            height = float(h) if h else None
        except ValueError:
            raise InputError(f"'{p}': <size> holds a non-numeric width or height") from None
        if not width or not height or width <= 0 or height <= 0:
            width = height = None  # VOC files often carry a zero or empty size: ignore it
    ships: list[Ship] = []
    objects = [c for c in root if isinstance(c.tag, str) and c.tag.lower() == "object"]
    for k, obj in enumerate(objects):
        where = f"'{p}' object {k}"
        bnd = _child(obj, "bndbox")
        if bnd is None:
            raise InputError(f"{where}: no <bndbox>")
        vals = {}
        for tag in ("xmin", "ymin", "xmax", "ymax"):
            t = _text(bnd, tag)
            try:
                vals[tag] = float(t) if t is not None else None
            except ValueError:
                vals[tag] = None
            if vals[tag] is None or not math.isfinite(vals[tag]):
                raise InputError(f"{where}: <bndbox> lacks a numeric <{tag}>")
        if vals["xmax"] < vals["xmin"] or vals["ymax"] < vals["ymin"]:
            raise InputError(f"{where}: <bndbox> has xmax < xmin or ymax < ymin")
        off = 1.0 if one_based else 0.0
        r0, c0 = vals["ymin"] - off, vals["xmin"] - off
        r1, c1 = vals["ymax"] - off + 1.0, vals["xmax"] - off + 1.0
        r0, c0 = max(r0, 0.0), max(c0, 0.0)
        if height is not None:
            r1 = min(r1, height)
        if width is not None:
            c1 = min(c1, width)
        if r1 <= r0 or c1 <= c0:
            raise InputError(f"{where}: <bndbox> lies outside the image")
        diff = _text(obj, "difficult")
        props: dict[str, Any] = {"name": _text(obj, "name") or "", "source": p.name}
        for tag in ("pose", "truncated"):
            t = _text(obj, tag)
            if t is not None:
                props[tag] = int(t) if t.isdigit() else t
        ships.append(Ship.from_bbox((r0, c0, r1, c1), difficult=diff in ("1", "true", "True"), **props))
    return ships


def load_voc_folder(folder: str | os.PathLike, one_based: bool = True) -> dict[str, list[Ship]]:
    """Ships of every ``*.xml`` in ``folder``, keyed by file stem (= the image stem), sorted."""
    d = Path(folder)
    _check_exists(d)
    if not d.is_dir():
        raise InputError(f"'{d}': not a folder")
    files = sorted(f for f in d.iterdir() if f.is_file() and f.suffix.lower() == ".xml")
    if not files:
        raise InputError(f"'{d}': folder holds no PASCAL-VOC .xml file")
    return {f.stem: load_voc(f, one_based=one_based) for f in files}


# ----------------------------------------------------------------------------- masks


def read_mask(path: str | os.PathLike) -> np.ndarray:
    """A boolean 2-D ship mask from an image, a ``.npy`` or a Zarr array/group (``mask``)."""
    p = Path(path)
    _check_exists(p)
    kind = _sniff(p)
    if kind == "zarr":
        return _read_zarr_mask(p)
    if kind == "npy":
        try:
            arr = np.load(p, allow_pickle=False)
        except Exception as exc:
            raise InputError(f"'{p}': not a readable .npy array ({type(exc).__name__})") from None
        if arr.ndim != 2 or not (arr.dtype == bool or np.issubdtype(arr.dtype, np.number)):
            raise InputError(f"'{p}': mask array must be 2-D numeric, got {arr.dtype} {arr.shape}")
        return np.asarray(arr != 0)
    if kind == "folder":
        raise InputError(f"'{p}': is a folder, expected a mask image")
    return _read_mask_image(p)


def _read_zarr_mask(p: Path) -> np.ndarray:
    import zarr

    try:
        node = zarr.open(str(p), mode="r")
    except Exception as exc:
        raise InputError(f"'{p}': not a readable Zarr store ({type(exc).__name__})") from None
    if isinstance(node, zarr.Group):
        try:
            node = node["mask"]
        except KeyError:
            raise InputError(f"'{p}': Zarr group has no 'mask' array") from None
        if not isinstance(node, zarr.Array):
            raise InputError(f"'{p}': 'mask' is not a Zarr array")
    if node.ndim != 2:
        raise InputError(f"'{p}': mask array must be 2-D, got shape {node.shape}")
    if not (node.dtype == bool or np.issubdtype(node.dtype, np.number)):
        raise InputError(f"'{p}': mask array must be numeric or boolean, got {node.dtype}")
    try:
        return np.asarray(node[...]) != 0
    except Exception as exc:
        raise InputError(f"'{p}': cannot read the mask array ({type(exc).__name__})") from None


def _read_mask_image(p: Path) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    arr = None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # PIL warns on corrupt metadata; a failure is reported below
            with Image.open(p) as im:
                if im.mode == "P":
                    im = im.convert("RGBA" if "transparency" in im.info else "RGB")
                elif im.mode in ("CMYK", "YCbCr", "LAB", "HSV"):
                    im = im.convert("RGB")
                arr = np.asarray(im)
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError, Image.DecompressionBombError):
        arr = None
    if arr is None and p.suffix.lower() in (".tif", ".tiff"):
        try:
            import tifffile

            arr = np.asarray(tifffile.imread(p))
        except Exception:
            arr = None
    if arr is None:
        raise InputError(f"'{p}': not a readable mask image")
    return mask_from_array(arr, where=f"'{p}'")


def mask_from_array(arr: np.ndarray, where: str = "mask") -> np.ndarray:
    """Ship pixels of a grey (H, W) or colour (H, W, 3|4) mask array (see module docstring)."""
    arr = np.asarray(arr)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.ndim == 2:
        return arr != 0
    if arr.ndim != 3 or arr.shape[2] not in (2, 3, 4):
        raise InputError(f"{where}: mask must be 2-D grey or RGB(A), got shape {arr.shape}")
    if arr.shape[2] == 2:  # grey + alpha
        return arr[..., 0] != 0
    rgb = arr[..., :3].astype(np.int32)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    if np.array_equal(r, g) and np.array_equal(g, b):
        return r != 0
    scale = 257 if arr.dtype == np.uint16 else 1
    green = (g >= GREEN_MIN * scale) & (g - np.maximum(r, b) >= GREEN_MARGIN * scale)
    if green.any():
        return green
    return (rgb != 0).any(axis=2)


def ships_from_mask(mask: np.ndarray) -> list[Ship]:
    """8-connected components of a boolean mask as ships (bbox and centroid from their pixels)."""
    from scipy import ndimage

    m = np.asarray(mask, dtype=bool)
    if m.ndim != 2:
        raise InputError(f"mask must be 2-D, got shape {m.shape}")
    labels, n = ndimage.label(m, structure=np.ones((3, 3), dtype=bool))
    if n == 0:
        return []
    slices = ndimage.find_objects(labels)
    idx = np.arange(1, n + 1)
    centres = ndimage.center_of_mass(m, labels, idx)
    areas = ndimage.sum_labels(m, labels, idx)
    ships = []
    for sl, cen, area in zip(slices, centres, areas):
        rs, cs = sl
        ships.append(
            Ship(
                (float(rs.start), float(cs.start), float(rs.stop), float(cs.stop)),
                (float(cen[0]) + 0.5, float(cen[1]) + 0.5),
                False,
                {"area_px": int(area)},
            )
        )
    return ships


# ----------------------------------------------------------------------------- dispatch


def truth_kind(path: str | os.PathLike) -> str:
    """'geojson', 'voc', 'voc-folder' or 'mask' for a truth path (no parsing beyond sniffing)."""
    p = Path(path)
    _check_exists(p)
    kind = _sniff(p)
    if kind == "folder":
        return "voc-folder"
    if kind in ("image", "npy", "zarr"):
        return "mask"
    return kind


def load_ships(
    path: str | os.PathLike, scene: str | None = None, one_based: bool = True
) -> tuple[list[Ship], np.ndarray | None]:
    """Ships of any truth source, and the boolean truth mask for a mask truth (else ``None``).

    A folder of VOC xml needs ``scene`` (the stem of the xml to use) unless it holds
    exactly one xml; see :func:`load_voc_folder` for all of them at once.
    """
    p = Path(path)
    kind = truth_kind(p)
    if kind == "geojson":
        return load_geojson(p), None
    if kind == "voc":
        return load_voc(p, one_based=one_based), None
    if kind == "voc-folder":
        files = sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() == ".xml")
        if not files:
            raise InputError(f"'{p}': folder holds no PASCAL-VOC .xml file")
        if scene is not None:
            stem = _scene_stem(scene)
            hit = [f for f in files if f.stem == stem]
            if not hit:
                raise InputError(f"'{p}': no '{stem}.xml' for scene '{stem}' ({len(files)} xml files)")
            return load_voc(hit[0], one_based=one_based), None
        if len(files) != 1:
            raise InputError(f"'{p}': {len(files)} xml files and no scene name to choose one (give one xml file)")
        return load_voc(files[0], one_based=one_based), None
    mask = read_mask(p)
    return ships_from_mask(mask), mask
