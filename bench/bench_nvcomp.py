"""GPU decoding of a scene store's chunks with nvCOMP, against the CPU's (issue 17: "decode on the
GPU itself (nvCOMP zstd ...): measure before choosing").

The scene stores hold float32 intensities in 512 x 512 inner chunks compressed by Zstd
(``sarship ingest``'s default codec; numcodecs writes standard zstd frames). This script makes
``--chunks`` such chunks of 1-look speckle (the band's content), compresses them with numcodecs'
Zstd, and decodes them

- on one CPU core with numcodecs (the reference, measured in the same run), and
- on the GPU with nvCOMP's batched Zstd decoder (``bitstream_kind=RAW``: plain zstd frames), the
  compressed bytes copied to the device as one buffer first (that copy is counted),

checks the GPU's output bit for bit against the CPU's, and prints GB/s (decoded bytes), Mpx/s
and the ratio GPU / one CPU core. Needs CuPy and ``nvidia-nvcomp-cu12`` or ``-cu13`` (with its
``nvidia-libnvcomp``), which sarship does not depend on.

Usage (on a GPU host)::

    python bench/bench_nvcomp.py [--chunks 144] [--repeat 3]
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--chunks", type=int, default=144, help="512 x 512 chunks (144: four 2048 tiles with halos)")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    import cupy as cp
    from numcodecs import Zstd
    from nvidia import nvcomp

    rng = np.random.default_rng(0)
    chunks = [rng.standard_exponential((512, 512), dtype=np.float32) for _ in range(a.chunks)]
    z = Zstd(level=3)
    comp = [z.encode(c) for c in chunks]
    raw = sum(c.nbytes for c in chunks)
    mpx = a.chunks * 512 * 512 / 1e6
    print(
        f"# nvCOMP {nvcomp.__version__} (CUDA {nvcomp.__cuda_version__}), CuPy {cp.__version__}, "
        f"{cp.cuda.runtime.getDeviceProperties(0)['name'].decode()}"
    )
    print(
        f"# {a.chunks} chunks of 512 x 512 float32 1-look speckle: {raw / 1e6:.1f} MB, compressed "
        f"{sum(len(c) for c in comp) / 1e6:.1f} MB"
    )
    cpu = float("inf")
    for _ in range(a.repeat):
        t = time.perf_counter()
        for c in comp:
            z.decode(c)
        cpu = min(cpu, time.perf_counter() - t)
    print(
        f"numcodecs Zstd, one CPU core (reference): {cpu * 1e3:.1f} ms, {raw / cpu / 1e9:.2f} GB/s, "
        f"{mpx / cpu:.0f} Mpx/s"
    )
    codec = nvcomp.Codec(algorithm="Zstd", bitstream_kind=nvcomp.BitstreamKind.RAW)
    host = np.frombuffer(b"".join(comp), np.uint8)
    offs = np.cumsum([0] + [len(c) for c in comp])
    gpu = float("inf")
    for _ in range(a.repeat + 1):  # the first call sets the decoder up
        cp.cuda.Device().synchronize()
        t = time.perf_counter()
        dev = cp.asarray(host)
        out = codec.decode(nvcomp.as_arrays([dev[offs[i] : offs[i + 1]] for i in range(a.chunks)]))
        cp.cuda.Device().synchronize()
        gpu = min(gpu, time.perf_counter() - t)
    same = all(
        cp.array_equal(cp.asarray(o).view(cp.float32).reshape(512, 512), cp.asarray(c)) for o, c in zip(out, chunks)
    )
    print(
        f"nvCOMP Zstd batch on the GPU (with the copy of the compressed bytes): {gpu * 1e3:.1f} ms, "
        f"{raw / gpu / 1e9:.2f} GB/s, {mpx / gpu:.0f} Mpx/s, {cpu / gpu:.1f}x one CPU core; "
        f"bit-identical to the CPU's: {same}"
    )


if __name__ == "__main__":
    main()
