#!/usr/bin/env python3
"""Times pycolmap / Ceres bundle adjustment on the problems written by `--bench ba -- --export DIR`.

Usage:
    cargo bench -p ggpt-sfm --bench ba -- --export /tmp/ba_bench
    python scripts/bench_pycolmap_ba.py /tmp/ba_bench [--repeats 5] [--threads 2]

Every `DIR/ba_*.json` problem (format written by the `ba` bench, pixel-centre convention) is loaded
into a `pycolmap.Reconstruction` in COLMAP coordinates (+0.5 px), with the same camera model,
shared camera, focal refinement, principal point held constant, loss, gauge (two cameras) and
stopping rules (max iterations, function / parameter tolerance) as the Rust solver, then solved
with `pycolmap.create_default_bundle_adjuster` (Ceres, DENSE_SCHUR for <= 50 images). The table
printed on stdout puts the Rust timings of `DIR/rust_results.json` beside the pycolmap ones.
Costs are Ceres' 0.5 * sum rho(|r|^2), comparable with the Rust costs.
"""

import argparse
import glob
import json
import os
import time

import numpy as np
import pycolmap


def build(problem):
    h, w = problem["image_size_hw"]
    cx, cy = w / 2.0, h / 2.0  # ((w-1)/2 + 0.5, (h-1)/2 + 0.5): COLMAP convention
    ks = problem["intrinsics"]
    shared = problem["shared_camera"]
    model = problem["model"]
    n = len(problem["cam_from_world"])

    def params(k):
        fx, fy = k[0], k[4]
        if model == "SIMPLE_PINHOLE":
            return [0.5 * (fx + fy), cx, cy]
        return [fx, fy, cx, cy]

    rec = pycolmap.Reconstruction()
    cam_ids = []
    for v in range(n if not shared else 1):
        cam = pycolmap.Camera(model=model, width=w, height=h, params=params(ks[v]), camera_id=v + 1)
        rec.add_camera_with_trivial_rig(cam)
        cam_ids.append(v + 1)
    cam_of_view = [cam_ids[0] if shared else cam_ids[v] for v in range(n)]

    obs_view = np.asarray(problem["obs_view"], dtype=np.int64)
    obs_point = np.asarray(problem["obs_point"], dtype=np.int64)
    obs_xy = np.asarray(problem["obs_xy"], dtype=np.float64) + 0.5
    points = np.asarray(problem["points"], dtype=np.float64)

    point_ids = [rec.add_point3D(points[j], pycolmap.Track()) for j in range(len(points))]
    order = np.lexsort((obs_point, obs_view))
    per_view = {v: [] for v in range(n)}
    for o in order:
        per_view[int(obs_view[o])].append(o)
    for v in range(n):
        m = np.asarray(problem["cam_from_world"][v], dtype=np.float64).reshape(3, 4)
        pts2d = [pycolmap.Point2D(obs_xy[o], point_ids[int(obs_point[o])]) for o in per_view[v]]
        image = pycolmap.Image(name=f"view_{v}", points2D=pycolmap.Point2DList(pts2d), camera_id=cam_of_view[v], image_id=v + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(m))
        for idx, o in enumerate(per_view[v]):
            rec.points3D[point_ids[int(obs_point[o])]].track.add_element(v + 1, idx)
    return rec


def options_for(problem, threads):
    opts = pycolmap.BundleAdjustmentOptions()
    opts.print_summary = False
    opts.refine_focal_length = bool(problem["refine_focal"])
    opts.refine_principal_point = False
    opts.refine_extra_params = False
    ceres = opts.ceres
    loss = problem["loss"]
    if loss["type"] == "cauchy":
        ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
        ceres.loss_function_scale = float(loss["scale"])
    so = ceres.solver_options
    so.max_num_iterations = int(problem["max_iterations"])
    so.function_tolerance = float(problem["function_tolerance"])
    so.parameter_tolerance = float(problem["parameter_tolerance"])
    so.num_threads = threads
    ceres.solver_options = so
    opts.ceres = ceres
    return opts


def config_for(problem, rec):
    cfg = pycolmap.BundleAdjustmentConfig()
    for image_id in sorted(rec.images.keys()):
        cfg.add_image(image_id)
    if problem["gauge"] == "two_cams":
        cfg.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    return cfg


def final_cost(summary):
    for obj in (summary, getattr(summary, "ceres_summary", None)):
        if obj is not None and hasattr(obj, "final_cost"):
            return obj.final_cost, obj.initial_cost, getattr(obj, "num_successful_steps", -1) + getattr(
                obj, "num_unsuccessful_steps", 0
            )
    return float("nan"), float("nan"), -1


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dir", help="directory written by the `ba` bench (`--export`)")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per problem (minimum reported)")
    ap.add_argument("--threads", type=int, default=-1, help="Ceres threads (-1 = all cores)")
    args = ap.parse_args()

    rust = {}
    rpath = os.path.join(args.dir, "rust_results.json")
    if os.path.exists(rpath):
        with open(rpath) as f:
            rust = {r["name"]: r for r in json.load(f)}

    print(f"pycolmap {pycolmap.__version__}")
    print(
        "| problem | observations | pycolmap iters | pycolmap wall (s) | pycolmap CPU (s) | pycolmap final cost "
        "| rust iters | rust wall (s) | rust CPU (s) | rust final cost | wall speed-up | CPU speed-up |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for path in sorted(glob.glob(os.path.join(args.dir, "ba_*.json"))):
        name = os.path.splitext(os.path.basename(path))[0]
        with open(path) as f:
            problem = json.load(f)
        best = None
        cpu_total = 0.0
        for _ in range(max(1, args.repeats)):
            rec = build(problem)  # not timed: problem construction
            opts = options_for(problem, args.threads)
            cfg = config_for(problem, rec)
            t0 = time.perf_counter()
            c0 = time.process_time()
            ba = pycolmap.create_default_bundle_adjuster(opts, cfg, rec)
            summary = ba.solve()
            cpu_total += time.process_time() - c0
            dt = time.perf_counter() - t0
            if best is None or dt < best[0]:
                best = (dt, summary)
        dt, summary = best
        cpu = cpu_total / max(1, args.repeats)
        cost, _, iters = final_cost(summary)
        r = rust.get(name)
        if r:
            speed = dt / r["seconds"] if r["seconds"] > 0 else float("nan")
            rcpu = r.get("cpu_seconds", float("nan"))
            cspeed = cpu / rcpu if rcpu and rcpu > 0 else float("nan")
            print(
                f"| {name} | {len(problem['obs_view'])} | {iters} | {dt:.4f} | {cpu:.4f} | {cost:.6e} | "
                f"{r['iterations']} | {r['seconds']:.4f} | {rcpu:.4f} | {r['final_cost']:.6e} | {speed:.2f}x | {cspeed:.2f}x |"
            )
        else:
            print(f"| {name} | {len(problem['obs_view'])} | {iters} | {dt:.4f} | {cpu:.4f} | {cost:.6e} | - | - | - | - | - | - |")


if __name__ == "__main__":
    main()
