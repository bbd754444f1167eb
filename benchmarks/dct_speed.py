"""DCT matrix form vs FFT form: time and exactness by size, on CPU and (if present) CUDA.

Justifies ``MATRIX_FORM_MAX_SIDE`` and checks that TF32 does not spoil the transform.

    python benchmarks/dct_speed.py --out benchmarks/results
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from datetime import datetime, timezone
from pathlib import Path

import torch

from assets_store.atomic import atomic_write_text
from morpheus_core.guidance.frequency import MATRIX_FORM_MAX_SIDE, dct2, idct2


def _time(fn, x: torch.Tensor, reps: int) -> float:
    for _ in range(3):
        fn(x)
    if x.is_cuda:
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(reps):
        fn(x)
    if x.is_cuda:
        torch.cuda.synchronize()
    return (time.perf_counter() - t0) / reps * 1e3


def measure(device: str, sizes: list[int], batch: int) -> list[dict]:
    rows = []
    for n in sizes:
        x = torch.randn(batch, 3, n, n, device=device)
        ref = dct2(x.double(), "fft")
        reps = 20 if device == "cuda" else 5
        row = {"device": device, "side": n, "batch": batch}
        for method in ("matrix", "fft"):
            row[f"{method}_ms"] = round(_time(lambda t, m=method: idct2(dct2(t, m), m), x, reps), 4)
            row[f"{method}_max_err"] = float((dct2(x, method).double() - ref).abs().max())
        rows.append(row)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results"))
    parser.add_argument("--sizes", type=int, nargs="+", default=[32, 64, 128, 256, 512, 1024])
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--tag", default=None, help="suffix of the result files (default: the device kind)")
    args = parser.parse_args()
    rows = measure("cpu", args.sizes, args.batch)
    tf32 = None
    if torch.cuda.is_available():
        torch.backends.cuda.matmul.allow_tf32 = True  # the worst case for a matrix-form DCT
        rows += measure("cuda", args.sizes, args.batch)
        x = torch.randn(4, 3, 64, 64, device="cuda")
        plain = (x.double() @ x.double().transpose(-1, -2) - x @ x.transpose(-1, -2)).abs().max()
        tf32 = {"plain_fp32_matmul_err_with_tf32": float(plain),
                "dct_matrix_err_with_tf32": float((dct2(x, "matrix").double() - dct2(x.double())).abs().max())}
    device = torch.cuda.get_device_name(0) if torch.cuda.is_available() else platform.processor() or "cpu"
    summary = {"date": datetime.now(timezone.utc).strftime("%Y-%m-%d"), "device": device,
               "torch": torch.__version__, "cpu_threads": torch.get_num_threads(),
               "matrix_form_max_side": MATRIX_FORM_MAX_SIDE, "rows": rows, "tf32_check": tf32}
    tag = args.tag or ("cuda" if torch.cuda.is_available() else "cpu")
    atomic_write_text(args.out / f"dct_speed_{tag}.json", json.dumps(summary, indent=2))
    lines = [f"# DCT round trip (dct2 + idct2), batch {args.batch}×3 channels", "",
             f"Device: {device}; torch {torch.__version__}; {torch.get_num_threads()} CPU threads; "
             f"date {summary['date']}. `auto` uses the matrix form up to side {MATRIX_FORM_MAX_SIDE}.", "",
             "| device | side | matrix (ms) | FFT (ms) | matrix max err | FFT max err |",
             "|---|---:|---:|---:|---:|---:|"]
    lines += [f"| {r['device']} | {r['side']} | {r['matrix_ms']:.3f} | {r['fft_ms']:.3f} | "
              f"{r['matrix_max_err']:.1e} | {r['fft_max_err']:.1e} |" for r in rows]
    if tf32:
        lines += ["", f"With TF32 enabled: a plain fp32 matmul errs by {tf32['plain_fp32_matmul_err_with_tf32']:.1e}; "
                  f"our matrix-form DCT by {tf32['dct_matrix_err_with_tf32']:.1e}."]
    atomic_write_text(args.out / f"dct_speed_{tag}.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
