"""`sarship ingest` of PolSARpro C3 / T3 / C2 folders and of covariance .npy arrays.

Conventions checked here (see the module doc of pipeline.readers):
store C = E[k k^H], k = [HH, sqrt2 HV, VV] (PolSARpro C3); T = E[k_p k_p^H],
k_p = (1/sqrt2)[HH+VV, HH-VV, 2 HV] = U k; C = U^H T U.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sarship.pipeline.errors import InputError
from sarship.pipeline.readers import C3_BASIS, PAULI_U, ingest, t3_to_c3

REAL_POLSAR = Path(__file__).resolve().parents[3] / "shared" / "data" / "real" / "polsar"

SIGMA = np.array(
    [
        [1.0, 0.10 + 0.05j, 0.45 - 0.10j],  # a sea-like HH/HV/VV covariance
        [0.10 - 0.05j, 0.08, 0.02 + 0.01j],
        [0.45 + 0.10j, 0.02 - 0.01j, 0.70],
    ]
)


# --------------------------------------------------------------------------- helpers


def scattering(shape, seed=0, sigma=SIGMA):
    """Circular complex Gaussian [HH, HV, VV] with E[s s^H] = sigma, shape (*shape, 3)."""
    rng = np.random.default_rng(seed)
    z = (rng.standard_normal((*shape, 3)) + 1j * rng.standard_normal((*shape, 3))) / math.sqrt(2)
    return z @ np.linalg.cholesky(sigma).T


def k_lex(s):
    return np.stack([s[..., 0], math.sqrt(2) * s[..., 1], s[..., 2]], axis=-1)


def k_pauli(s):
    hh, hv, vv = s[..., 0], s[..., 1], s[..., 2]
    return np.stack([hh + vv, hh - vv, 2 * hv], axis=-1) / math.sqrt(2)


def outer(k):
    return k[..., :, None] * np.conj(k[..., None, :])


def multilook(M, f):
    H, W = M.shape[0] // f, M.shape[1] // f
    return M[: H * f, : W * f].reshape(H, f, W, f, *M.shape[2:]).mean(axis=(1, 3))


def looked(shape, seed=0, f=2):
    """(C, T) float64 matrices of f x f looks from the same scattering vectors."""
    s = scattering((shape[0] * f, shape[1] * f), seed)
    return multilook(outer(k_lex(s)), f), multilook(outer(k_pauli(s)), f)


def f32_elements(M):
    """The float32 element values a PolSARpro folder holds, as a float64 complex matrix."""
    n = M.shape[-1]
    out = np.zeros(M.shape, np.complex128)
    for i in range(n):
        out[..., i, i] = M[..., i, i].real.astype(np.float32)
        for j in range(i + 1, n):
            v = M[..., i, j].real.astype(np.float32) + 1j * M[..., i, j].imag.astype(np.float32)
            out[..., i, j], out[..., j, i] = v, np.conj(v)
    return out


def write_header(path: Path, H, W, dtype=4, order=0, offset=0, interleave="bsq", bands=1):
    path.write_text(
        "ENVI\ndescription = {\nPolSARpro File Imported to ENVI}\n"
        f"samples = {W}\nlines = {H}\nbands = {bands}\nheader offset = {offset}\n"
        f"file type = ENVI Standard\ndata type = {dtype}\ninterleave = {interleave}\n"
        f"byte order = {order}\nband names = {{\n{path.name[:-4]} }}\n"
    )


def write_folder(d: Path, M, prefix="C", order=0, config=True, headers=True, polar_type=None, f64=False):
    """A PolSARpro folder of matrix M (H, W, n, n); returns d."""
    d.mkdir(parents=True, exist_ok=True)
    H, W, n = M.shape[0], M.shape[1], M.shape[2]
    dt = np.dtype(("<" if order == 0 else ">") + ("f8" if f64 else "f4"))
    for i in range(n):
        for j in range(i, n):
            e = f"{prefix}{i + 1}{j + 1}"
            parts = (
                [(e, M[..., i, i].real)]
                if i == j
                else [(f"{e}_real", M[..., i, j].real), (f"{e}_imag", M[..., i, j].imag)]
            )
            for stem, v in parts:
                np.ascontiguousarray(v, dtype=dt).tofile(d / f"{stem}.bin")
                if headers:
                    write_header(d / f"{stem}.bin.hdr", H, W, order=order, dtype=5 if f64 else 4)
    if config:
        pt = polar_type or ("full" if n == 3 else "pp1")
        (d / "config.txt").write_text(
            f"Nrow\n{H}\n---------\nNcol\n{W}\n---------\nPolarCase\nmonostatic\n---------\nPolarType\n{pt}\n"
        )
    return d


def read(sc, name):
    return np.asarray(sc.array(name)[...])


def stored(sc, n):
    """The scene's full Hermitian matrices (H, W, n, n), complex128."""
    H, W = sc.shape
    out = np.zeros((H, W, n, n), np.complex128)
    for i in range(n):
        out[..., i, i] = read(sc, f"c{i + 1}{i + 1}")
        for j in range(i + 1, n):
            v = read(sc, f"c{i + 1}{j + 1}")
            out[..., i, j], out[..., j, i] = v, np.conj(v)
    return out


def leftovers(folder: Path):
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(".") or p.suffix == ".zarr")


SHAPE = (64, 88)  # not a multiple of the tile: partial edge tiles


# --------------------------------------------------------------------------- conventions


def test_pauli_transform_convention():
    U = PAULI_U
    np.testing.assert_allclose(U.conj().T @ U, np.eye(3), atol=1e-15)
    s = scattering((50,), seed=3)
    np.testing.assert_allclose(k_pauli(s), k_lex(s) @ U.T, atol=1e-12)  # k_p = U k
    C, T = outer(k_lex(s)), outer(k_pauli(s))
    np.testing.assert_allclose(t3_to_c3(T), C, atol=1e-12)  # C = U^H T U, exactly
    np.testing.assert_allclose(np.einsum("ia,...ab,jb->...ij", U, C, U.conj()), T, atol=1e-12)
    # the store's C22 is 2 |HV|^2 and C13 is HH VV^*
    np.testing.assert_allclose(t3_to_c3(T)[:, 1, 1].real, 2 * np.abs(s[:, 1]) ** 2, atol=1e-12)
    np.testing.assert_allclose(t3_to_c3(T)[:, 0, 2], s[:, 0] * np.conj(s[:, 2]), atol=1e-12)


# --------------------------------------------------------------------------- C3 / T3 / C2


def test_c3_folder_exact(tmp_path):
    C, _ = looked(SHAPE, seed=1)
    d = write_folder(tmp_path / "C3", C)
    sc = ingest([d], tmp_path / "c.zarr", tile=32)
    assert sc.kind == "covariance" and sc.shape == SHAPE
    assert sc.variables == {
        "c11": "float32",
        "c12": "complex64",
        "c13": "complex64",
        "c22": "float32",
        "c23": "complex64",
        "c33": "float32",
    }
    want = f32_elements(C)
    np.testing.assert_array_equal(stored(sc, 3), want)  # float32 values stored exactly
    a = sc.attrs
    assert a["format"] == "PolSARpro C3" and a["covariance_basis"] == C3_BASIS == "lexicographic [HH, sqrt2 HV, VV]"
    assert a["source"] == ["C3"] and "C12_imag.bin" in a["source_files"] and a["byte_order"] == "little-endian"
    assert a["polsarpro_config"]["PolarType"] == "full"
    assert a["looks_source"].startswith("estimated: MoLC") and 2.0 < sc.looks < 8.0  # 4 looks
    # the folder may also be named by its config.txt or its C11.bin (or the header)
    for p in (d / "config.txt", d / "C11.bin", d / "C11.bin.hdr"):
        sc2 = ingest([p], tmp_path / "c2.zarr", tile=16)
        np.testing.assert_array_equal(stored(sc2, 3), want)


def test_t3_folder_converted_to_c3(tmp_path):
    C, T = looked(SHAPE, seed=2)
    np.testing.assert_allclose(t3_to_c3(T), C, atol=1e-12)
    d = write_folder(tmp_path / "T3", T, prefix="T")
    sc = ingest([d], tmp_path / "t.zarr", tile=32)
    assert sc.kind == "covariance" and len(sc.variables) == 6
    assert sc.attrs["format"] == "PolSARpro T3 -> C3" and sc.attrs["covariance_basis"] == C3_BASIS
    got = stored(sc, 3)
    # exact conversion of the float32 T values (only the final rounding to float32 differs)
    want = t3_to_c3(f32_elements(T))
    scale = np.abs(want).max()
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=2e-7 * scale)
    # and the C built directly from k_lex, up to the float32 rounding of T
    np.testing.assert_allclose(got, C, rtol=1e-5, atol=1e-6 * scale)
    assert np.all(read(sc, "c11") > 0) and np.all(read(sc, "c33") > 0)


def test_t3_folder_round_trip_with_npy(tmp_path):
    C, T = looked(SHAPE, seed=4)
    np.save(tmp_path / "c.npy", C.astype(np.complex64))
    a = ingest([tmp_path / "c.npy"], tmp_path / "a.zarr", tile=32)
    b = ingest([write_folder(tmp_path / "T3", T, prefix="T")], tmp_path / "b.zarr", tile=32)
    assert a.attrs["covariance_basis"] == b.attrs["covariance_basis"] == C3_BASIS
    assert a.attrs["format"] == "npy covariance C3"
    scale = np.abs(C).max()
    np.testing.assert_allclose(stored(b, 3), stored(a, 3), rtol=1e-5, atol=1e-6 * scale)
    # and the C3 folder written from the .npy data gives the .npy scene exactly
    c = ingest([write_folder(tmp_path / "C3", C.astype(np.complex64))], tmp_path / "c.zarr", tile=32)
    np.testing.assert_array_equal(stored(c, 3), stored(a, 3))


def test_big_endian_header(tmp_path):
    C, _ = looked(SHAPE, seed=5)
    le = ingest([write_folder(tmp_path / "le", C)], tmp_path / "le.zarr", tile=32)
    be = ingest([write_folder(tmp_path / "be", C, order=1)], tmp_path / "be.zarr", tile=32)
    assert be.attrs["byte_order"] == "big-endian"
    np.testing.assert_array_equal(stored(be, 3), stored(le, 3))
    # data type 5 (float64), big-endian: rounded to the store's float32 / complex64
    f8 = ingest([write_folder(tmp_path / "f8", C, order=1, f64=True)], tmp_path / "f8.zarr", tile=32)
    assert f8.attrs["sample_dtype"] == "float64"
    np.testing.assert_array_equal(stored(f8, 3), stored(le, 3))


def test_c2_dual_pol_folder(tmp_path):
    s = scattering((SHAPE[0] * 2, SHAPE[1] * 2), seed=6)[..., [2, 1]]  # [VV, VH]
    C2 = multilook(outer(s), 2)
    d = write_folder(tmp_path / "C2", C2, polar_type="pp2")
    sc = ingest([d], tmp_path / "d.zarr", tile=32)
    assert sc.kind == "covariance"
    assert sc.variables == {"c11": "float32", "c12": "complex64", "c22": "float32"}
    np.testing.assert_array_equal(stored(sc, 2), f32_elements(C2))
    assert sc.attrs["format"] == "PolSARpro C2"
    assert sc.attrs["covariance_basis"].startswith("dual-pol [VV, VH]")
    assert sc.attrs["polarisations"] == ["vv", "vh"]
    # without config.txt the element files say C2
    d2 = write_folder(tmp_path / "C2b", C2, config=False)
    sc2 = ingest([d2], tmp_path / "d2.zarr", tile=32)
    np.testing.assert_array_equal(stored(sc2, 2), f32_elements(C2))
    assert sc2.attrs["covariance_basis"].startswith("dual-pol [k1, k2]")


def test_single_look_folder_has_one_look(tmp_path):
    s = scattering(SHAPE, seed=7)
    sc = ingest([write_folder(tmp_path / "T3", outer(k_pauli(s)), prefix="T")], tmp_path / "s.zarr", tile=32)
    assert sc.looks == 1.0 and sc.attrs["looks_source"].startswith("estimated: rank-one")
    np.save(tmp_path / "c.npy", outer(k_lex(s)).astype(np.complex64))
    sc = ingest([tmp_path / "c.npy"], tmp_path / "n.zarr", tile=32)
    assert sc.looks == 1.0 and sc.attrs["looks_source"].startswith("estimated: rank-one")
    sc = ingest([tmp_path / "c.npy"], tmp_path / "n.zarr", tile=32, looks=3)  # argument wins
    assert sc.looks == 3.0


def test_headerless_folder_uses_config(tmp_path):
    C, _ = looked(SHAPE, seed=8)
    sc = ingest([write_folder(tmp_path / "C3", C, headers=False)], tmp_path / "h.zarr", tile=32)
    np.testing.assert_array_equal(stored(sc, 3), f32_elements(C))
    assert "no ENVI header" in sc.attrs["polsarpro_note"]


def test_streams_tile_by_tile(tmp_path, monkeypatch):
    """Element files are memory-mapped and read one tile window at a time."""
    C, _ = looked(SHAPE, seed=9)
    d = write_folder(tmp_path / "C3", C)
    seen = []
    real = np.memmap.__getitem__

    def spy(self, idx):
        if isinstance(idx, tuple) and len(idx) == 2 and all(isinstance(i, slice) for i in idx):
            seen.append((idx[0].stop - idx[0].start, idx[1].stop - idx[1].start))
        return real(self, idx)

    monkeypatch.setattr(np.memmap, "__getitem__", spy)
    ingest([d], tmp_path / "c.zarr", tile=16)
    assert seen and max(h for h, _ in seen) <= 16 and max(w for _, w in seen) <= 16


# --------------------------------------------------------------------------- errors


def _fail(tmp_path, inp, match, names):
    out = tmp_path / "out.zarr"
    with pytest.raises(InputError, match=match) as e:
        ingest([inp], out, tile=32)
    msg = str(e.value)
    assert "\n" not in msg and names in msg, msg
    assert not out.exists() and leftovers(tmp_path) == []
    return msg


def _c3(tmp_path, **kw):
    C, _ = looked((16, 24), seed=10)
    return write_folder(tmp_path / "C3", C, **kw)


def test_missing_element_files(tmp_path):
    d = _c3(tmp_path)
    (d / "C23_imag.bin").unlink()
    (d / "C13_real.bin").unlink()
    msg = _fail(tmp_path, d, "missing element file", "C13_real.bin")
    assert "C23_imag.bin" in msg and "C3" in msg


def test_size_mismatch(tmp_path):
    d = _c3(tmp_path)
    with open(d / "C22.bin", "ab") as f:
        f.write(b"\0\0\0\0")
    msg = _fail(tmp_path, d, "header/size mismatch", "C22.bin")
    assert "1540 bytes" in msg and "= 1536" in msg


def test_header_offset_counts(tmp_path):
    d = _c3(tmp_path)
    write_header(d / "C11.bin.hdr", 16, 24, offset=8)  # the file has no 8-byte header
    _fail(tmp_path, d, "header/size mismatch", "C11.bin")
    # a real header offset is skipped
    v = np.fromfile(d / "C11.bin", "<f4")
    (d / "C11.bin").write_bytes(b"PSPHEADR" + v.tobytes())
    sc = ingest([d], tmp_path / "ok.zarr", tile=32)
    np.testing.assert_array_equal(read(sc, "c11").ravel(), v)


@pytest.mark.parametrize(
    "field,value,match",
    [
        ("dtype", 6, "unsupported ENVI data type 6"),
        ("dtype", 2, "unsupported ENVI data type 2"),
        ("interleave", "tiled", "unsupported interleave"),
        ("bands", 2, "2 bands"),
    ],
)
def test_unsupported_header(tmp_path, field, value, match):
    d = _c3(tmp_path)
    write_header(d / "C12_real.bin.hdr", 16, 24, **{field: value})
    _fail(tmp_path, d, match, "C12_real.bin.hdr")


def test_unequal_sizes_and_config_mismatch(tmp_path):
    d = _c3(tmp_path)
    np.zeros((16, 20), "<f4").tofile(d / "C33.bin")
    write_header(d / "C33.bin.hdr", 16, 20)
    _fail(tmp_path, d, "equal sizes", "C33.bin")
    d = _c3(tmp_path / "b")
    (d / "config.txt").write_text("Nrow\n17\n---------\nNcol\n24\n---------\nPolarType\nfull\n")
    _fail(tmp_path / "b", d, "says Nrow 17", "config.txt")


def test_not_an_envi_header_and_misc(tmp_path):
    d = _c3(tmp_path)
    (d / "C11.bin.hdr").write_text("samples = 24\n")
    _fail(tmp_path, d, "not an ENVI header", "C11.bin.hdr")
    with pytest.raises(InputError, match="pass the folder"):
        ingest([d / "C12_real.bin"], tmp_path / "o.zarr")
    np.save(tmp_path / "x.npy", np.ones((16, 24), np.float32))
    with pytest.raises(InputError, match="cannot be combined"):
        ingest([d, tmp_path / "x.npy"], tmp_path / "o.zarr")


def test_failure_keeps_existing_scene(tmp_path):
    C, _ = looked((16, 24), seed=11)
    good = write_folder(tmp_path / "good", C)
    out = tmp_path / "out.zarr"
    ingest([good], out, tile=32)
    before = stored(ingest([out], tmp_path / "copy.zarr"), 3)
    bad = write_folder(tmp_path / "bad", C * 2)
    (bad / "C33.bin").write_bytes(b"\0" * 10)
    with pytest.raises(InputError, match="C33.bin"):
        ingest([bad], out, tile=32)
    from sarship.pipeline.scene import open_scene

    np.testing.assert_array_equal(stored(open_scene(out), 3), before)


def test_cli_ingest_folder(tmp_path):
    C, _ = looked((16, 24), seed=12)
    d = write_folder(tmp_path / "C3", C)
    env = dict(os.environ)
    r = subprocess.run(
        [sys.executable, "-m", "sarship", "ingest", str(d), "--out", str(tmp_path / "c.zarr")],
        capture_output=True,
        text=True,
        env=env,
        cwd=Path(__file__).resolve().parents[2],
    )
    if r.returncode != 0 and "No module named" in r.stderr:
        pytest.skip(f"sarship not runnable as a module: {r.stderr.strip()[:200]}")
    assert r.returncode == 0, r.stderr
    assert "kind=covariance" in r.stdout
    (d / "C11.bin").write_bytes(b"\0" * 8)
    r = subprocess.run(
        [sys.executable, "-m", "sarship", "ingest", str(d), "--out", str(tmp_path / "e.zarr")],
        capture_output=True,
        text=True,
        env=env,
        cwd=Path(__file__).resolve().parents[2],
    )
    assert r.returncode == 2 and "C11.bin" in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


# --------------------------------------------------------------------------- real data


def _real_files():
    return sorted(REAL_POLSAR.glob("*.npy")) if REAL_POLSAR.is_dir() else []


@pytest.mark.realdata
@pytest.mark.skipif(not _real_files(), reason=f"real PolSAR samples absent: no *.npy in {REAL_POLSAR}")
@pytest.mark.parametrize("name", [p.name for p in _real_files()] or ["none"])
def test_real_polsar_npy(tmp_path, name):
    p = REAL_POLSAR / name
    C = np.load(p)
    n = C.shape[-1]
    # the source: Hermitian per pixel, real non-negative diagonal
    scale = np.abs(C).max()
    np.testing.assert_allclose(C, np.conj(np.swapaxes(C, -1, -2)), atol=1e-5 * scale)
    sc = ingest([p], tmp_path / "c.zarr", tile=128)
    assert sc.kind == "covariance" and len(sc.variables) == n * (n + 1) // 2
    for i in range(n):
        d = read(sc, f"c{i + 1}{i + 1}")
        assert d.dtype == np.float32 and np.all(np.isfinite(d)) and np.all(d >= 0)
        assert np.mean(d > 0) > 0.99  # a few no-data zeros in the Sentinel-1 crops
        np.testing.assert_array_equal(d, C[..., i, i].real)
        for j in range(i + 1, n):
            np.testing.assert_array_equal(read(sc, f"c{i + 1}{j + 1}"), C[..., i, j])
    # nearly positive semi-definite: |c_ij|^2 <= c_ii c_jj (a handful of AIRSAR / Pi-SAR pixels
    # exceed it by up to 6 % in the shipped data, so allow 0.1 % of pixels)
    full = stored(sc, n)
    for i in range(n):
        for j in range(i + 1, n):
            bad = np.abs(full[..., i, j]) ** 2 > full[..., i, i].real * full[..., j, j].real * (1 + 1e-4) + 1e-30
            assert bad.mean() < 1e-3
    assert sc.attrs["covariance_basis"] == (C3_BASIS if n == 3 else "dual-pol [k1, k2] as given (channels unknown)")
    assert sc.looks is not None and 0.3 < sc.looks < 20
    if n == 3:
        # the same data as a PolSARpro C3 folder: identical; as T3 (U C U^H): equal to rounding
        c3 = ingest([write_folder(tmp_path / "C3", C)], tmp_path / "f.zarr", tile=128)
        np.testing.assert_array_equal(stored(c3, 3), stored(sc, 3))
        T = np.einsum("ia,...ab,jb->...ij", PAULI_U, C.astype(np.complex128), PAULI_U.conj())
        t3 = ingest([write_folder(tmp_path / "T3", T, prefix="T")], tmp_path / "t.zarr", tile=128)
        np.testing.assert_allclose(stored(t3, 3), stored(sc, 3), rtol=1e-4, atol=1e-6 * scale)
