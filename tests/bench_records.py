"""Records as ``benchmarks/early_stop.py`` writes them, for the tests of the summaries that read them."""

from __future__ import annotations

from benchmarks.error_time import POINTS


def glb_record(base: str, scene: str, seed: int, psnr: float, oracle: str = "stochastic") -> dict:
    """One fixed-schedule run whose GLB scores ``psnr`` (earlier stages a little less)."""
    points = [{"stage": s, "wall_s": 10.0 * (i + 1), "novel_psnr": psnr - 0.5 * (len(POINTS) - 1 - i),
               "detail_psnr": psnr + 5, "chamfer": 0.01, "fscore": 0.99} for i, s in enumerate(POINTS)]
    return {"base": base, "scene": scene, "seed": seed, "early_stop": False, "oracle": oracle, "points": points,
            "machine": "NVIDIA Test GPU, torch x", "date": "2026-12-07"}
