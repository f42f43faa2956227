"""Recipes for public labelled SAR ship datasets with their official splits: fetch, verify, convert.

The data never enter the repository: a recipe fetches a dataset from where its authors publish
it, checks it against the published counts, the official split rules and (where one is
committed) a sha256 manifest, and converts it to the layout ``bench/realdata_split_eval.py``
reads. Licences are stated per dataset (:data:`DATASETS`); none of these releases grants
redistribution, so a recipe only points to the official source and never re-hosts a file.

Usage::

    python bench/datasets.py list
    python bench/datasets.py fetch NAME --to DIR [--from PATH] [--no-manifest]
    python bench/datasets.py verify NAME --data RAW [--no-manifest]
    python bench/datasets.py convert NAME --data RAW --to DIR [--no-manifest]
    python bench/datasets.py manifest NAME --data RAW      # writes bench/datasets/NAME.sha256

``fetch`` obtains the raw release into ``DIR/NAME-raw`` (``git clone`` at the pinned commit for a
git-hosted set; for a set published as an archive on a file host, which needs a browser or the
host's own client, ``--from`` names the downloaded archive or unpacked folder), then verifies and
converts it into ``DIR/NAME``. ``verify`` and ``convert`` run those steps alone on a raw copy.

Converted layout (``DIR/NAME``, published by a rename only when complete)::

    dataset.json             name, source, commit, licence, citation, counts per split
    images/<id><ext>         the release's image files, byte for byte
    truth/<id>.geojson       the ship boxes, a FeatureCollection in the detections schema
                             (``properties.bbox_px`` = [row0, col0, row1, col1], half-open;
                             docs/interfaces/files.md), readable by ``sarship score``
    splits/<split>.txt       image ids, one a line, sorted: ``train``, ``test`` and, where the
                             release defines them, ``test_inshore`` and ``test_offshore``

Manifest (``bench/datasets/NAME.sha256``): ``sha256sum`` format, one line per file of the raw
release that the recipe reads (images and annotations of every split), paths relative to the
release root. ``verify`` refuses a copy that differs from a committed manifest in any byte or
file; without a committed manifest it refuses too, unless ``--no-manifest`` says to check the
published counts and split rules only. ``manifest`` writes one from a copy you trust (after
``verify --no-manifest`` passed on it), to be committed.

Bad input (unknown dataset, missing folder, a copy that fails a check, an output that exists)
exits 2 with one line on stderr naming the problem; nothing is left at the output then.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
MANIFESTS = Path(__file__).resolve().parent / "datasets"

#: Splits a converted dataset may hold, in report order.
SPLITS = ("train", "test", "test_inshore", "test_offshore")


class DatasetError(Exception):
    """A one-line problem with a dataset copy or a recipe argument (exit status 2)."""


@dataclass(frozen=True)
class Item:
    """One labelled image of a raw release: its image file and its annotation file."""

    id: str
    image: Path
    annotation: Path


@dataclass(frozen=True)
class Dataset:
    """A recipe: where the release lives, its licence, its layout and its published counts."""

    name: str
    title: str
    citation: str
    licence: str
    source: str
    #: ``git`` (cloned at ``commit``) or ``archive`` (downloaded by the user, given with ``--from``).
    kind: str
    layout: Callable[[Path], dict[str, dict[str, Item]]]
    #: Images per split as published; ``None`` for a split whose count the release does not state.
    counts: dict[str, int | None]
    total_images: int
    commit: str | None = None
    download: tuple[str, ...] = ()
    #: Extra checks of the parsed splits (beyond counts and disjointness): list of problems.
    rules: Callable[[dict[str, dict[str, Item]]], list[str]] | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)


# --------------------------------------------------------------------------------------
# official split rules and layouts


def ssdd_is_test(image_id: str) -> bool:
    """The SSDD official training-test division: an image is in the test set when its file
    number ends in 1 or 9 (``000001``, ``000009``, ``000011`` ...), else in the training set.

    Raises :class:`DatasetError` for an id that is not a number."""
    if not image_id.isdigit():
        raise DatasetError(f"SSDD image id '{image_id}' is not a file number")
    return int(image_id) % 10 in (1, 9)


def _pairs(img_dir: Path, ann_dir: Path, exts: tuple[str, ...]) -> dict[str, Item]:
    """Images of ``img_dir`` (by suffix) paired with ``ann_dir/<stem>.xml``; every image needs one."""
    for d in (img_dir, ann_dir):
        if not d.is_dir():
            raise DatasetError(f"missing folder '{d}'")
    out: dict[str, Item] = {}
    for p in sorted(img_dir.iterdir()):
        if not p.is_file() or p.suffix.lower() not in exts:
            continue
        ann = ann_dir / f"{p.stem}.xml"
        if not ann.is_file():
            raise DatasetError(f"image '{p}' has no annotation '{ann.name}' in '{ann_dir}'")
        if p.stem in out:
            raise DatasetError(f"two images with id '{p.stem}' in '{img_dir}'")
        out[p.stem] = Item(p.stem, p, ann)
    if not out:
        raise DatasetError(f"folder '{img_dir}' holds no image ({', '.join(exts)})")
    return out


def ssdd_official_layout(root: Path) -> dict[str, dict[str, Item]]:
    """The BBox-SSDD part of the official release (``Official-SSDD-OPEN``): the folder holding
    ``BBox_SSDD/voc_style/JPEGImages_{train,test,test_inshore,test_offshore}`` and the
    matching ``Annotations_*`` folders (PASCAL-VOC xml). ``root`` may be that folder or one
    level above it (an archive unpacked into a folder of its own)."""
    cands = [root, *sorted(p for p in root.iterdir() if p.is_dir())] if root.is_dir() else []
    base = next((c / "BBox_SSDD" / "voc_style" for c in cands if (c / "BBox_SSDD" / "voc_style").is_dir()), None)
    if base is None:
        raise DatasetError(f"'{root}': no BBox_SSDD/voc_style folder (the layout of the official SSDD release)")
    return {s: _pairs(base / f"JPEGImages_{s}", base / f"Annotations_{s}", (".jpg", ".jpeg", ".png")) for s in SPLITS}


def ssdd_rules(parsed: dict[str, dict[str, Item]]) -> list[str]:
    """The official division holds: test ids end in 1 or 9, train ids do not; the test set is
    exactly the union of its inshore and offshore parts, which do not overlap."""
    bad: list[str] = []
    wrong_test = sorted(i for i in parsed["test"] if not ssdd_is_test(i))
    wrong_train = sorted(i for i in parsed["train"] if ssdd_is_test(i))
    if wrong_test:
        bad.append(f"test images whose number ends in neither 1 nor 9: {', '.join(wrong_test[:5])}")
    if wrong_train:
        bad.append(f"training images whose number ends in 1 or 9: {', '.join(wrong_train[:5])}")
    ins, off, test = set(parsed["test_inshore"]), set(parsed["test_offshore"]), set(parsed["test"])
    if ins & off:
        bad.append(f"images both inshore and offshore: {', '.join(sorted(ins & off)[:5])}")
    if ins | off != test:
        diff = sorted((ins | off) ^ test)
        bad.append(f"inshore + offshore differ from the test set in {len(diff)} images: {', '.join(diff[:5])}")
    return bad


def dssdd_layout(root: Path) -> dict[str, dict[str, Item]]:
    """DSSDD as its repository holds it: ``originalTIF/{train,test}/<id>.tif`` (the 16-bit
    dual-polarisation originals) with ``annotations/HorizontalBox/{train,test}/<id>.xml``."""
    if not root.is_dir():
        raise DatasetError(f"'{root}': not a folder")
    return {
        s: _pairs(root / "originalTIF" / s, root / "annotations" / "HorizontalBox" / s, (".tif", ".tiff"))
        for s in ("train", "test")
    }


DATASETS: dict[str, Dataset] = {
    "ssdd_official": Dataset(
        name="ssdd_official",
        title="SSDD, official release (BBox-SSDD): RADARSAT-2, TerraSAR-X, Sentinel-1 chips, 1-15 m",
        citation="zhang2021ssdd",
        licence=(
            "no licence is stated: the release page asks users to cite the paper; redistribution "
            "terms are not given, so the recipe only points to the official download"
        ),
        source="https://github.com/TianwenZhang0825/Official-SSDD",
        commit="e29d3b7ec481cc457c49d51e575451f11f6f489c",  # the README that gives the download links
        kind="archive",
        download=(
            "https://drive.google.com/file/d/1glNJUGotrbEyk43twwB9556AdngJsynZ/view (Official-SSDD-OPEN.rar)",
            "https://pan.baidu.com/s/1Lpg28ZvMSgNXq00abHMZ5Q (password 2021)",
        ),
        layout=ssdd_official_layout,
        # 928 / 232 follow from the division rule over ids 1..1160; 46 / 186 inshore / offshore
        # as a third-party copy of the release describes it (not checked against the paper here).
        counts={"train": 928, "test": 232, "test_inshore": 46, "test_offshore": 186},
        total_images=1160,
        rules=ssdd_rules,
        notes=("test = file numbers ending in 1 or 9; inshore/offshore = the release's test subfolders",),
    ),
    "dssdd": Dataset(
        name="dssdd",
        title="DSSDD: Sentinel-1 IW dual-polarisation (VV/VH) slices 256 x 256, 16-bit originals",
        citation="hu2021dssdd",
        licence=(
            "no licence is stated in the repository (its README is a title); the recipe clones it "
            "from its authors and never re-hosts a file"
        ),
        source="https://github.com/liyiniiecas/A_Dual-polarimetric_SAR_Ship_Detection_Dataset",
        commit="b93c0ae86dbfcb7548cc3113a54cf11736c3ed77",
        kind="git",
        layout=dssdd_layout,
        counts={"train": None, "test": None},
        total_images=1236,
        notes=("train/test = the repository's folders; the release defines no inshore/offshore protocol",),
    ),
}


def get(name: str) -> Dataset:
    """The recipe called ``name``; :class:`DatasetError` naming the known ones otherwise."""
    try:
        return DATASETS[name]
    except KeyError:
        raise DatasetError(f"unknown dataset '{name}' (known: {', '.join(sorted(DATASETS))})") from None


# --------------------------------------------------------------------------------------
# checks


def check(ds: Dataset, parsed: dict[str, dict[str, Item]]) -> list[str]:
    """Problems of a parsed release: published counts, disjoint train/test, the dataset's rules."""
    bad: list[str] = []
    for split, want in ds.counts.items():
        got = len(parsed.get(split, {}))
        if want is not None and got != want:
            bad.append(f"{split}: {got} images, the release publishes {want}")
    train, test = set(parsed.get("train", {})), set(parsed.get("test", {}))
    if train & test:
        bad.append(f"images in both train and test: {', '.join(sorted(train & test)[:5])}")
    if len(train | test) != ds.total_images:
        bad.append(f"{len(train | test)} images in train + test, the release publishes {ds.total_images}")
    if ds.rules is not None:
        bad += ds.rules(parsed)
    return bad


def sha256_file(path: Path, block: int = 1 << 20) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(block):
            h.update(chunk)
    return h.hexdigest()


def release_files(parsed: dict[str, dict[str, Item]]) -> list[Path]:
    """Every file the recipe reads (images and annotations of all splits), each once, sorted."""
    files = {p for items in parsed.values() for it in items.values() for p in (it.image, it.annotation)}
    return sorted(files)


def _root_of(files: list[Path]) -> Path:
    return Path(os.path.commonpath([str(p) for p in files])) if len(files) > 1 else files[0].parent


def manifest_text(root: Path, files: list[Path]) -> str:
    """``sha256sum``-format lines for ``files``, paths relative to ``root``, sorted by path."""
    lines = [f"{sha256_file(p)}  {p.relative_to(root).as_posix()}" for p in files]
    return "".join(line + "\n" for line in sorted(lines, key=lambda s: s.split("  ", 1)[1]))


def read_manifest(path: Path) -> dict[str, str]:
    """``{relative path: sha256}`` of a ``sha256sum``-format file; :class:`DatasetError` on a bad line."""
    out: dict[str, str] = {}
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        digest, sep, rel = line.partition("  ")
        if not sep or len(digest) != 64 or any(c not in "0123456789abcdef" for c in digest) or not rel:
            raise DatasetError(f"'{path}' line {n}: not '<sha256>  <path>'")
        out[rel] = digest
    return out


def check_manifest(root: Path, files: list[Path], manifest: dict[str, str]) -> list[str]:
    """Files missing from, extra to, or differing from the manifest (paths relative to ``root``)."""
    have = {p.relative_to(root).as_posix(): p for p in files}
    bad: list[str] = []
    missing = sorted(set(manifest) - set(have))
    extra = sorted(set(have) - set(manifest))
    if missing:
        bad.append(f"{len(missing)} files of the manifest are missing, e.g. {missing[0]}")
    if extra:
        bad.append(f"{len(extra)} files are not in the manifest, e.g. {extra[0]}")
    differ = [rel for rel in sorted(set(have) & set(manifest)) if sha256_file(have[rel]) != manifest[rel]]
    if differ:
        bad.append(f"{len(differ)} files differ from the manifest (sha256), e.g. {differ[0]}")
    return bad


def manifest_path(ds: Dataset) -> Path:
    return MANIFESTS / f"{ds.name}.sha256"


def verify(
    ds: Dataset, raw: Path, use_manifest: bool = True, manifest: Path | None = None
) -> tuple[dict[str, dict[str, Item]], Path]:
    """Parse the raw release at ``raw`` and check it; return (parsed splits, release root).

    Raises :class:`DatasetError` with every problem found in one line."""
    parsed = ds.layout(Path(raw))
    bad = check(ds, parsed)
    files = release_files(parsed)
    root = _root_of(files)
    if use_manifest:
        mpath = manifest or manifest_path(ds)
        if not mpath.is_file():
            raise DatasetError(
                f"no manifest committed for '{ds.name}' ({mpath.relative_to(REPO) if mpath.is_relative_to(REPO) else mpath}):"
                f" check a copy with --no-manifest, then write one with 'manifest'"
            )
        bad += check_manifest(root, files, read_manifest(mpath))
    if bad:
        raise DatasetError(f"'{raw}' is not the {ds.name} release: " + "; ".join(bad))
    return parsed, root


# --------------------------------------------------------------------------------------
# conversion


def _truth_geojson(ann: Path) -> dict:
    from sarship.pipeline.errors import InputError
    from sarship.pipeline.products.truth import load_voc

    try:
        ships = load_voc(ann)
    except InputError as exc:
        raise DatasetError(str(exc)) from None
    return {"type": "FeatureCollection", "features": [s.to_feature() for s in ships]}


def convert(ds: Dataset, parsed: dict[str, dict[str, Item]], to: Path) -> Path:
    """Write the converted layout of ``parsed`` at ``to/<name>`` (see the module docstring).

    Built in a temporary folder beside it and renamed into place when complete; refuses an
    existing ``to/<name>``."""
    final = Path(to) / ds.name
    if final.exists():
        raise DatasetError(f"'{final}' already exists: remove it or convert elsewhere")
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{ds.name}.partial-", dir=final.parent))
    try:
        (tmp / "images").mkdir()
        (tmp / "truth").mkdir()
        (tmp / "splits").mkdir()
        items: dict[str, Item] = {}
        for split_items in parsed.values():
            for i, it in split_items.items():
                if i in items and items[i].image.read_bytes() != it.image.read_bytes():
                    raise DatasetError(f"image id '{i}' names two different images ('{items[i].image}', '{it.image}')")
                items.setdefault(i, it)
        ships: dict[str, int] = {}
        for i, it in sorted(items.items()):
            shutil.copyfile(it.image, tmp / "images" / f"{i}{it.image.suffix.lower()}")
            doc = _truth_geojson(it.annotation)
            ships[i] = len(doc["features"])
            (tmp / "truth" / f"{i}.geojson").write_text(json.dumps(doc))
        counts = {}
        for split in SPLITS:
            if split in parsed:
                ids = sorted(parsed[split])
                (tmp / "splits" / f"{split}.txt").write_text("".join(f"{i}\n" for i in ids))
                counts[split] = {"images": len(ids), "ships": sum(ships[i] for i in ids)}
        meta = {
            "name": ds.name,
            "title": ds.title,
            "source": ds.source,
            "commit": ds.commit,
            "download": list(ds.download),
            "licence": ds.licence,
            "citation": ds.citation,
            "notes": list(ds.notes),
            "splits": counts,
        }
        (tmp / "dataset.json").write_text(json.dumps(meta, indent=1) + "\n")
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


def read_split(path: Path) -> list[str]:
    """Image ids of a ``splits/<split>.txt`` (one a line; blank lines ignored), in file order."""
    return [line.strip() for line in Path(path).read_text().splitlines() if line.strip()]


# --------------------------------------------------------------------------------------
# fetching


def _run(cmd: list[str]) -> None:
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        msg = (r.stderr or r.stdout).strip().splitlines()
        raise DatasetError(f"'{' '.join(cmd[:3])} ...' failed: {msg[-1] if msg else f'exit {r.returncode}'}")


def fetch_git(ds: Dataset, dest: Path) -> Path:
    """Clone ``ds.source`` into ``dest`` and check out the pinned commit (git verifies every
    object of that commit by its hash); refuses an existing ``dest``."""
    if dest.exists():
        raise DatasetError(f"'{dest}' already exists: remove it or fetch elsewhere")
    if shutil.which("git") is None:
        raise DatasetError("git is not installed: it is needed to fetch a git-hosted dataset")
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.partial-", dir=dest.parent))
    try:
        _run(["git", "clone", "--quiet", "--no-checkout", ds.source, str(tmp / "repo")])
        _run(["git", "-C", str(tmp / "repo"), "checkout", "--quiet", "--detach", str(ds.commit)])
        head = subprocess.run(
            ["git", "-C", str(tmp / "repo"), "rev-parse", "HEAD"], capture_output=True, text=True
        ).stdout.strip()
        if head != ds.commit:
            raise DatasetError(f"checked out {head or 'nothing'}, not the pinned commit {ds.commit}")
        os.replace(tmp / "repo", dest)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return dest


def unpack(src: Path, dest: Path) -> Path:
    """A downloaded release at ``src`` as a folder at ``dest``: a folder is used in place (``dest``
    is then ``src``); a zip/tar archive is unpacked by :func:`shutil.unpack_archive`; a ``.rar``
    (how SSDD is published) by ``unrar``, ``7z`` or ``bsdtar``, whichever is installed."""
    src = Path(src)
    if src.is_dir():
        return src
    if not src.is_file():
        raise DatasetError(f"'{src}': no such file or folder")
    if dest.exists():
        raise DatasetError(f"'{dest}' already exists: remove it or fetch elsewhere")
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.partial-", dir=dest.parent))
    try:
        if src.suffix.lower() == ".rar":
            tools = {
                "unrar": ["unrar", "x", "-idq", str(src), str(tmp) + os.sep],
                "7z": ["7z", "x", "-y", f"-o{tmp}", str(src)],
                "bsdtar": ["bsdtar", "-xf", str(src), "-C", str(tmp)],
            }
            tool = next((t for t in tools if shutil.which(t)), None)
            if tool is None:
                raise DatasetError(
                    f"'{src}': a .rar archive needs unrar, 7z or bsdtar; or unpack it yourself and pass the folder"
                )
            _run(tools[tool])
        else:
            try:
                shutil.unpack_archive(str(src), str(tmp))
            except (shutil.ReadError, ValueError) as exc:
                raise DatasetError(f"'{src}': cannot unpack ({exc})") from None
        os.replace(tmp, dest)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return dest


def fetch(ds: Dataset, to: Path, source: Path | None = None, use_manifest: bool = True) -> Path:
    """Raw release into ``to/<name>-raw`` (or ``source`` in place when it is a folder), verified,
    then converted into ``to/<name>``; returns the converted folder."""
    to = Path(to)
    to.mkdir(parents=True, exist_ok=True)
    raw = to / f"{ds.name}-raw"
    if source is not None:
        raw = unpack(Path(source), raw)
    elif ds.kind == "git":
        raw = fetch_git(ds, raw)
    else:
        raise DatasetError(
            f"'{ds.name}' is published as an archive on a file host that needs a browser: download it from "
            f"{ds.download[0] if ds.download else ds.source} and pass it with --from"
        )
    parsed, _ = verify(ds, raw, use_manifest)
    return convert(ds, parsed, to)


# --------------------------------------------------------------------------------------
# command line


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("list", help="the recipes, their sources and licences")
    p = sub.add_parser("fetch", help="fetch, verify and convert a dataset")
    p.add_argument("name")
    p.add_argument("--to", type=Path, required=True, help="folder for NAME-raw and the converted NAME")
    p.add_argument("--from", dest="source", type=Path, help="a downloaded archive or unpacked folder")
    p.add_argument("--no-manifest", action="store_true", help="check counts and split rules only")
    p = sub.add_parser("verify", help="check a raw copy")
    p.add_argument("name")
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--no-manifest", action="store_true")
    p = sub.add_parser("convert", help="verify a raw copy and convert it")
    p.add_argument("name")
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--to", type=Path, required=True)
    p.add_argument("--no-manifest", action="store_true")
    p = sub.add_parser("manifest", help="write bench/datasets/NAME.sha256 from a copy that passes verify")
    p.add_argument("name")
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--out", type=Path, help="where to write it (default: bench/datasets/NAME.sha256)")
    a = ap.parse_args(argv)
    try:
        if a.cmd == "list":
            for ds in DATASETS.values():
                print(
                    f"{ds.name}: {ds.title}\n  source: {ds.source}"
                    + (f" @ {ds.commit}" if ds.commit else "")
                    + "".join(f"\n  download: {d}" for d in ds.download)
                    + f"\n  licence: {ds.licence}\n  manifest: "
                    + ("committed" if manifest_path(ds).is_file() else "none committed")
                )
            return 0
        ds = get(a.name)
        if a.cmd == "fetch":
            out = fetch(ds, a.to, a.source, not a.no_manifest)
            print(f"{ds.name}: converted into {out}")
        elif a.cmd == "verify":
            parsed, _ = verify(ds, a.data, not a.no_manifest)
            print(f"{ds.name}: OK (" + ", ".join(f"{s} {len(v)}" for s, v in parsed.items()) + " images)")
        elif a.cmd == "convert":
            parsed, _ = verify(ds, a.data, not a.no_manifest)
            print(f"{ds.name}: converted into {convert(ds, parsed, a.to)}")
        elif a.cmd == "manifest":
            parsed, root = verify(ds, a.data, use_manifest=False)
            out = a.out or manifest_path(ds)
            text = manifest_text(root, release_files(parsed))
            out.parent.mkdir(parents=True, exist_ok=True)
            tmp = out.with_name(out.name + ".partial")
            tmp.write_text(text)
            os.replace(tmp, out)
            print(f"{ds.name}: {text.count(chr(10))} files written to {out}")
    except DatasetError as exc:
        print(f"datasets.py: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"datasets.py: {exc.filename or ''}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
