"""Refines a scene folder through the Python package, as `ggpt-infer run --scene DIR --weights
shipped --seed SEED --out OUT` does (docs/python.md, "Measured": the overhead of the Python call
is timed against that command on the same scene, whole process against whole process).

    python crates/ggpt-py/bench/refine_scene.py SCENE OUT [--seed 42] [--min-chunk-pixels N ...]
"""

from __future__ import annotations

import argparse
import time

import ggpt_rs as ggpt


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("scene")
    p.add_argument("out")
    p.add_argument("--seed", type=int, default=42)
    p.add_argument("--min-chunk-pixels", type=int)
    p.add_argument("--min-chunk-dlt", type=int)
    p.add_argument("--max-chunk-pixels", type=int)
    a = p.parse_args()
    t0 = time.perf_counter()
    scene = ggpt.read_scene(a.scene)
    out = ggpt.refine(
        scene,
        seed=a.seed,
        progress=False,
        min_chunk_pixels=a.min_chunk_pixels,
        min_chunk_dlt=a.min_chunk_dlt,
        max_chunk_pixels=a.max_chunk_pixels,
    )
    out.save(a.out, error_maps=False)
    print(f"refined {out.stats['counts']['chunks']} chunks in {time.perf_counter() - t0:.2f} s")


if __name__ == "__main__":
    main()
