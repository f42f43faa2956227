"""bench/datasets.py (fetch / verify / convert of public SAR ship datasets with their official
splits) and bench/realdata_split_eval.py (scores on the official test split, offshore and inshore
apart), on small synthetic copies of the releases' layouts: no network, no real data."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

REPO = Path(__file__).resolve().parents[2]


def _load(name: str):
    """A bench/ script as a module, under a name of its own (``datasets`` is also a PyPI package)."""
    key = f"sarship_bench_{name}"
    if key not in sys.modules:
        spec = importlib.util.spec_from_file_location(key, REPO / "bench" / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        sys.modules[key] = mod  # dataclasses need the module registered while it executes
        spec.loader.exec_module(mod)
    return sys.modules[key]


ds_mod = _load("datasets")
ev = _load("realdata_split_eval")

#: The tiny SSDD copy: ids 1..20; test = numbers ending in 1 or 9.
IDS = [f"{i:06d}" for i in range(1, 21)]
TEST = [i for i in IDS if int(i) % 10 in (1, 9)]  # 000001, 000009, 000011, 000019
INSHORE = ["000001", "000011"]
OFFSHORE = ["000009", "000019"]


def _voc(path: Path, boxes: list[tuple[int, int, int, int]], size=(40, 30)) -> None:
    objs = "".join(
        f"<object><name>ship</name><difficult>0</difficult><bndbox><xmin>{x0}</xmin><ymin>{y0}</ymin>"
        f"<xmax>{x1}</xmax><ymax>{y1}</ymax></bndbox></object>"
        for x0, y0, x1, y1 in boxes
    )
    path.write_text(
        f"<annotation><size><width>{size[0]}</width><height>{size[1]}</height><depth>3</depth></size>"
        f"{objs}</annotation>"
    )


def _img(path: Path, seed: int, shape=(30, 40)) -> None:
    rng = np.random.default_rng(seed)
    Image.fromarray(rng.integers(0, 255, shape, dtype=np.uint8)).save(path)


def make_ssdd(root: Path, test=TEST, inshore=INSHORE, offshore=OFFSHORE) -> Path:
    """The official release's BBox-SSDD layout with 20 tiny chips, one ship each."""
    base = root / "Official-SSDD-OPEN" / "BBox_SSDD" / "voc_style"
    train = [i for i in IDS if i not in test]
    for split, ids in (("train", train), ("test", test), ("test_inshore", inshore), ("test_offshore", offshore)):
        (base / f"JPEGImages_{split}").mkdir(parents=True)
        (base / f"Annotations_{split}").mkdir(parents=True)
        for i in ids:
            _img(base / f"JPEGImages_{split}" / f"{i}.jpg", int(i))
            _voc(base / f"Annotations_{split}" / f"{i}.xml", [(3, 4, 12, 9)])
    return root


@pytest.fixture()
def tiny_ssdd():
    """The ssdd_official recipe with the tiny copy's counts in place of the published ones."""
    return dataclasses.replace(
        ds_mod.DATASETS["ssdd_official"],
        counts={"train": 16, "test": 4, "test_inshore": 2, "test_offshore": 2},
        total_images=20,
    )


# -------------------------------------------------------------------------------- split rules


def test_ssdd_official_division_rule():
    assert [ds_mod.ssdd_is_test(i) for i in ("000001", "000009", "000011", "000019", "001159")] == [True] * 5
    assert [ds_mod.ssdd_is_test(i) for i in ("000002", "000010", "000018", "001160")] == [False] * 4
    with pytest.raises(ds_mod.DatasetError, match="not a file number"):
        ds_mod.ssdd_is_test("ship01")
    # the published counts the recipe enforces: 1160 = 928 + 232; 232 = 46 inshore + 186 offshore
    ssdd = ds_mod.DATASETS["ssdd_official"]
    assert ssdd.counts == {"train": 928, "test": 232, "test_inshore": 46, "test_offshore": 186}
    assert ssdd.total_images == 1160
    assert sum(ds_mod.ssdd_is_test(f"{i:06d}") for i in range(1, 1161)) == 232


def test_ssdd_layout_and_checks(tmp_path, tiny_ssdd):
    parsed, root = ds_mod.verify(tiny_ssdd, make_ssdd(tmp_path), use_manifest=False)
    assert sorted(parsed["test"]) == TEST
    assert sorted(parsed["test_inshore"]) == INSHORE and sorted(parsed["test_offshore"]) == OFFSHORE
    assert len(parsed["train"]) == 16
    assert root.name == "voc_style"
    # the release's published counts: the tiny copy is refused, saying why
    with pytest.raises(ds_mod.DatasetError, match="train: 16 images, the release publishes 928"):
        ds_mod.verify(ds_mod.DATASETS["ssdd_official"], tmp_path, use_manifest=False)


def test_ssdd_rules_catch_a_wrong_division(tmp_path, tiny_ssdd):
    # 000005 in the test set, 000009 missing from it; inshore and offshore share 000001
    bad = make_ssdd(
        tmp_path,
        test=["000001", "000005", "000011", "000019"],
        inshore=["000001", "000011"],
        offshore=["000001", "000019"],
    )
    with pytest.raises(ds_mod.DatasetError) as exc:
        ds_mod.verify(tiny_ssdd, bad, use_manifest=False)
    msg = str(exc.value)
    assert "\n" not in msg
    assert "000005" in msg and "ends in neither 1 nor 9" in msg
    assert "training images whose number ends in 1 or 9: 000009" in msg
    assert "both inshore and offshore: 000001" in msg


def test_missing_annotation_and_folder(tmp_path, tiny_ssdd):
    root = make_ssdd(tmp_path)
    base = root / "Official-SSDD-OPEN" / "BBox_SSDD" / "voc_style"
    (base / "Annotations_test" / "000009.xml").unlink()
    with pytest.raises(ds_mod.DatasetError, match="000009.jpg' has no annotation"):
        ds_mod.verify(tiny_ssdd, root, use_manifest=False)
    with pytest.raises(ds_mod.DatasetError, match="no BBox_SSDD/voc_style folder"):
        ds_mod.verify(tiny_ssdd, tmp_path / "Official-SSDD-OPEN" / "BBox_SSDD", use_manifest=False)


def test_dssdd_layout(tmp_path):
    for split, ids in (("train", ["000001", "000002"]), ("test", ["000003"])):
        (tmp_path / "originalTIF" / split).mkdir(parents=True)
        (tmp_path / "annotations" / "HorizontalBox" / split).mkdir(parents=True)
        for i in ids:
            (tmp_path / "originalTIF" / split / f"{i}.tif").write_bytes(b"II*\x00" + i.encode())
            _voc(tmp_path / "annotations" / "HorizontalBox" / split / f"{i}.xml", [(44, 78, 50, 100)], (256, 256))
    tiny = dataclasses.replace(ds_mod.DATASETS["dssdd"], total_images=3)
    parsed, _ = ds_mod.verify(tiny, tmp_path, use_manifest=False)
    assert {s: sorted(v) for s, v in parsed.items()} == {"train": ["000001", "000002"], "test": ["000003"]}
    with pytest.raises(ds_mod.DatasetError, match="3 images in train \\+ test, the release publishes 1236"):
        ds_mod.verify(ds_mod.DATASETS["dssdd"], tmp_path, use_manifest=False)


# -------------------------------------------------------------------------------- manifest


def test_manifest_round_trip_and_tamper(tmp_path, tiny_ssdd):
    raw = make_ssdd(tmp_path / "raw")
    parsed, root = ds_mod.verify(tiny_ssdd, raw, use_manifest=False)
    man = tmp_path / "tiny.sha256"
    man.write_text(ds_mod.manifest_text(root, ds_mod.release_files(parsed)))
    lines = man.read_text().splitlines()
    assert len(lines) == 2 * (20 + 4)  # images + annotations of train, test, inshore, offshore
    assert "  JPEGImages_test/000001.jpg" in "\n".join(lines)
    ds_mod.verify(tiny_ssdd, raw, manifest=man)  # passes
    # no committed manifest: refused unless --no-manifest
    with pytest.raises(ds_mod.DatasetError, match="no manifest committed for 'ssdd_official'"):
        ds_mod.verify(tiny_ssdd, raw, manifest=tmp_path / "none.sha256")
    # one changed byte, one extra file: both named
    img = root / "JPEGImages_test" / "000009.jpg"
    img.write_bytes(img.read_bytes()[:-1] + b"\x00")
    _img(root / "JPEGImages_train" / "000020.jpg", 99)
    _img(root / "JPEGImages_train" / "000021.jpg", 98)  # an extra chip breaks the counts too
    _voc(root / "Annotations_train" / "000021.xml", [(1, 1, 3, 3)])
    with pytest.raises(ds_mod.DatasetError) as exc:
        ds_mod.verify(tiny_ssdd, raw, manifest=man)
    msg = str(exc.value)
    assert "files differ from the manifest (sha256), e.g. JPEGImages_test/000009.jpg" in msg
    assert "not in the manifest, e.g. Annotations_train/000021.xml" in msg
    with pytest.raises(ds_mod.DatasetError, match="not '<sha256>  <path>'"):
        (tmp_path / "bad.sha256").write_text("abc  x.jpg\n")
        ds_mod.read_manifest(tmp_path / "bad.sha256")


# -------------------------------------------------------------------------------- convert


def test_convert_layout_truth_and_publish(tmp_path, tiny_ssdd):
    parsed, _ = ds_mod.verify(tiny_ssdd, make_ssdd(tmp_path / "raw"), use_manifest=False)
    out = ds_mod.convert(tiny_ssdd, parsed, tmp_path / "data")
    assert out == tmp_path / "data" / "ssdd_official"
    assert sorted(p.name for p in out.iterdir()) == ["dataset.json", "images", "splits", "truth"]
    assert len(list((out / "images").iterdir())) == 20
    assert ds_mod.read_split(out / "splits" / "test.txt") == TEST
    assert ds_mod.read_split(out / "splits" / "test_inshore.txt") == INSHORE
    assert ds_mod.read_split(out / "splits" / "test_offshore.txt") == OFFSHORE
    # the image bytes are the release's; the VOC box (1-based, inclusive) becomes a half-open bbox_px
    src = tmp_path / "raw" / "Official-SSDD-OPEN" / "BBox_SSDD" / "voc_style" / "JPEGImages_test" / "000009.jpg"
    assert (out / "images" / "000009.jpg").read_bytes() == src.read_bytes()
    feats = json.loads((out / "truth" / "000009.geojson").read_text())["features"]
    assert [f["properties"]["bbox_px"] for f in feats] == [[3, 2, 9, 12]]  # xmin 3 ymin 4 xmax 12 ymax 9
    meta = json.loads((out / "dataset.json").read_text())
    assert meta["splits"]["test"] == {"images": 4, "ships": 4}
    assert meta["licence"].startswith("no licence is stated") and meta["citation"] == "zhang2021ssdd"
    assert not [p for p in (tmp_path / "data").iterdir() if p.name.startswith(".")]  # no partial left
    with pytest.raises(ds_mod.DatasetError, match="already exists"):
        ds_mod.convert(tiny_ssdd, parsed, tmp_path / "data")


def test_convert_leaves_nothing_on_bad_annotation(tmp_path, tiny_ssdd):
    raw = make_ssdd(tmp_path / "raw")
    bad = raw / "Official-SSDD-OPEN" / "BBox_SSDD" / "voc_style" / "Annotations_train" / "000004.xml"
    bad.write_text("<annotation><object><name>ship</name></object></annotation>")
    parsed, _ = ds_mod.verify(tiny_ssdd, raw, use_manifest=False)
    with pytest.raises(ds_mod.DatasetError, match="000004.xml' object 0: no <bndbox>"):
        ds_mod.convert(tiny_ssdd, parsed, tmp_path / "data")
    assert list((tmp_path / "data").iterdir()) == []


# -------------------------------------------------------------------------------- fetch


def test_fetch_from_git_at_the_pinned_commit(tmp_path):
    """A git-hosted release is cloned and checked out at the pinned commit (a local repository
    stands in for the published one); a commit that is not the pinned one is refused."""
    src = tmp_path / "upstream"
    for split, ids in (("train", ["000001", "000002"]), ("test", ["000003"])):
        (src / "originalTIF" / split).mkdir(parents=True)
        (src / "annotations" / "HorizontalBox" / split).mkdir(parents=True)
        for i in ids:
            _img(src / "originalTIF" / split / f"{i}.tif", int(i))
            _voc(src / "annotations" / "HorizontalBox" / split / f"{i}.xml", [(5, 5, 10, 20)], (40, 30))
    git = ["git", "-C", str(src), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run(["git", "init", "-q", str(src)], check=True)
    subprocess.run(git + ["add", "."], check=True)
    subprocess.run(git + ["commit", "-qm", "v1"], check=True)
    pinned = subprocess.run(git + ["rev-parse", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
    (src / "originalTIF" / "test" / "000003.tif").write_bytes(b"later change")
    subprocess.run(git + ["commit", "-qam", "v2"], check=True)
    tiny = dataclasses.replace(ds_mod.DATASETS["dssdd"], source=str(src), commit=pinned, total_images=3)
    out = ds_mod.fetch(tiny, tmp_path / "data", use_manifest=False)
    assert ds_mod.read_split(out / "splits" / "test.txt") == ["000003"]
    raw = tmp_path / "data" / "dssdd-raw" / "originalTIF" / "test" / "000003.tif"
    assert raw.read_bytes() != b"later change"  # the pinned commit, not the newest
    assert (out / "images" / "000003.tif").read_bytes() == raw.read_bytes()
    wrong = dataclasses.replace(tiny, commit="0" * 40)
    with pytest.raises(ds_mod.DatasetError, match="failed"):
        ds_mod.fetch(wrong, tmp_path / "other", use_manifest=False)
    assert not (tmp_path / "other" / "dssdd-raw").exists()


def test_fetch_archive_needs_from_and_unpacks_zip(tmp_path, tiny_ssdd):
    with pytest.raises(ds_mod.DatasetError, match="download it from https://drive.google.com/.* --from"):
        ds_mod.fetch(tiny_ssdd, tmp_path / "data")
    raw = make_ssdd(tmp_path / "dl")
    arc = tmp_path / "Official-SSDD-OPEN.zip"
    with zipfile.ZipFile(arc, "w") as z:
        for p in sorted(raw.rglob("*")):
            z.write(p, p.relative_to(raw))
    out = ds_mod.fetch(tiny_ssdd, tmp_path / "data", source=arc, use_manifest=False)
    assert ds_mod.read_split(out / "splits" / "test_offshore.txt") == OFFSHORE
    assert (tmp_path / "data" / "ssdd_official-raw" / "Official-SSDD-OPEN" / "BBox_SSDD").is_dir()


def test_cli_bad_input_exits_2_with_one_line(tmp_path, capsys):
    assert ds_mod.main(["verify", "nosuch", "--data", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown dataset 'nosuch' (known: dssdd, ssdd_official)" in err
    make_ssdd(tmp_path / "raw")
    assert (
        ds_mod.main(
            [
                "convert",
                "ssdd_official",
                "--data",
                str(tmp_path / "raw"),
                "--to",
                str(tmp_path / "data"),
                "--no-manifest",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "the release publishes 928" in err
    assert not (tmp_path / "data" / "ssdd_official").exists()
    assert ds_mod.main(["list"]) == 0
    out = capsys.readouterr().out
    assert "ssdd_official" in out and "licence: no licence is stated" in out


# -------------------------------------------------------------------------------- the split evaluation


def test_iou_matching_is_one_to_one_at_half():
    t = np.array([[0, 0, 10, 10], [20, 20, 30, 30]], float)
    d = np.array(
        [
            [0, 0, 10, 10],  # IoU 1 with ship 0
            [0, 0, 10, 6],  # IoU 0.6 with ship 0: taken already -> false alarm
            [20, 20, 30, 25],  # IoU exactly 0.5 with ship 1 -> hit
            [50, 50, 60, 60],
        ],
        float,
    )
    assert ev.match_iou(d, t) == [(0, 0), (2, 1)]
    c = ev.iou_counts(d, t)
    assert c == {"n_truth": 2, "n_detections": 4, "n_hit": 2}
    r = ev.ratios(c)
    assert (r["precision"], r["recall"], r["f1"], r["n_false"]) == (0.5, 1.0, 2 * 2 / 6, 2)
    assert ev.match_iou(np.array([[20, 20, 30, 24]], float), t) == []  # IoU 0.4
    assert ev.ratios({"n_truth": 0, "n_detections": 0, "n_hit": 0})["f1"] == 1.0


def test_subsets_every_and_bad_folder(tmp_path, tiny_ssdd):
    parsed, _ = ds_mod.verify(tiny_ssdd, make_ssdd(tmp_path / "raw"), use_manifest=False)
    out = ds_mod.convert(tiny_ssdd, parsed, tmp_path / "data")
    s = ev.load_subsets(out)
    assert s == {"test_offshore": OFFSHORE, "test_inshore": INSHORE, "test": TEST}
    assert ev.load_subsets(out, every=2) == {
        "test_offshore": ["000009"],
        "test_inshore": ["000001"],
        "test": ["000001", "000011"],
    }
    with pytest.raises(ev.EvalError, match="not a dataset converted by bench/datasets.py"):
        ev.load_subsets(tmp_path)
    (out / "truth" / "000019.geojson").unlink()
    with pytest.raises(ev.EvalError, match="'000019' has no truth/000019.geojson"):
        ev.load_subsets(out)
    assert ev.main(["--data", str(out), "--detectors", "nosuch"]) == 2


def _ship_chip(path: Path, seed: int, boxes) -> None:
    """Rayleigh sea (8-bit amplitude) with bright rectangular ships."""
    rng = np.random.default_rng(seed)
    a = rng.rayleigh(20.0, (160, 160))
    for r0, c0, r1, c1 in boxes:
        a[r0:r1, c0:c1] = 250.0
    Image.fromarray(np.clip(a, 0, 255).astype(np.uint8)).save(path)


def test_report_and_table_per_subset():
    """Summed counts per subset, both matchers, and one table row per detector and subset."""
    rows = {
        "ca_cfar": {
            "000001": {
                "iou50": {"n_truth": 3, "n_detections": 4, "n_hit": 2},
                "ours": {"n_truth": 3, "n_detections": 4, "n_hit": 3},
            },
            "000009": {
                "iou50": {"n_truth": 1, "n_detections": 1, "n_hit": 1},
                "ours": {"n_truth": 1, "n_detections": 1, "n_hit": 1},
            },
        }
    }
    subsets = {"test_offshore": ["000009"], "test_inshore": ["000001"], "test": ["000001", "000009"]}
    rep = ev.report(rows, subsets)
    assert rep["ca_cfar"]["test_offshore"]["iou50"]["f1"] == 1.0
    ins = rep["ca_cfar"]["test_inshore"]
    assert (ins["iou50"]["precision"], ins["iou50"]["recall"], ins["iou50"]["n_false"]) == (0.5, 2 / 3, 2)
    assert ins["ours"]["fom"] == 3 / 4  # 3 hits / (1 false + 3 ships)
    allt = rep["ca_cfar"]["test"]["iou50"]
    assert (allt["n_truth"], allt["n_detections"], allt["n_hit"], allt["f1"]) == (4, 5, 3, 6 / 9)
    md = ev.markdown(rep, subsets, every=2)
    assert md.count("\n| ca_cfar |") == 3
    assert "| ca_cfar | inshore | 1 / 3 | 0.500 / 0.667 / 0.571 (2) | 0.750 / 1.000 / 0.857 (1), 0.750 |" in md
    assert "One image in 2 of each subset" in md


def test_split_eval_end_to_end(tmp_path, client):
    """A converted test image through ingest + run_detection at ca_cfar's defaults (the path
    users' scenes take): its two ships found under both matchers."""
    out = tmp_path / "ds"
    for d in ("images", "truth", "splits"):
        (out / d).mkdir(parents=True)
    from sarship.pipeline.products.truth import Ship

    boxes = [(40, 50, 52, 56), (100, 30, 106, 48)]
    _ship_chip(out / "images" / "000009.png", 0, boxes)
    feats = [Ship.from_bbox(b).to_feature() for b in boxes]
    (out / "truth" / "000009.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    (out / "splits" / "test.txt").write_text("000009\n")
    (out / "splits" / "test_offshore.txt").write_text("000009\n")
    (out / "dataset.json").write_text("{}")
    subsets = ev.load_subsets(out)
    assert subsets == {"test_offshore": ["000009"], "test": ["000009"]}
    rows = ev.run(out, ["ca_cfar"], subsets, client, tmp_path / "work", threads=1, log=lambda m: None)
    rep = ev.report(rows, subsets)["ca_cfar"]
    for s in subsets:
        assert rep[s]["iou50"]["n_truth"] == 2
        assert rep[s]["iou50"]["n_hit"] == 2 and rep[s]["ours"]["n_hit"] == 2
