#!/usr/bin/env python3
"""Reads a COLMAP sparse model with pycolmap and prints a JSON summary.

Usage: python3 scripts/check_colmap_model.py DIR [--skip-error-check]

DIR is a model folder (cameras/images/points3D .bin or .txt), e.g. the `sparse/0/` written by
`ggpt-sfm run --out OUT`; `OUT` itself (or `OUT/sparse`) is accepted and resolved to
`OUT/sparse/0`. The model is loaded with `pycolmap.Reconstruction(DIR)`, then checked
independently of the writer:

* every POINTS2D entry with a POINT3D_ID names an existing 3D point whose track holds that
  (image_id, point2D_idx), and every track element names an existing image / POINTS2D entry that
  points back to the point; no track has two elements in one image;
* cameras, poses and points are finite;
* each point is reprojected with its images' cameras and poses (`Image.project_point`); the
  per-observation errors give `recomputed_mean_reprojection_error` (mean over points of the
  per-point mean, the definition of COLMAP's `compute_mean_reprojection_error`), the mean over
  observations and the maximum; a stored point ERROR that differs from the recomputed one by more
  than 1e-3 px is an error unless --skip-error-check (points with an observation behind its
  camera are only counted);
* tracks shorter than 2 are counted (`short_tracks`), not an error (COLMAP reads them; the
  `ggpt-sfm` export writes none).

Printed JSON (stdout): pycolmap_version, path, num_cameras, num_images, num_reg_images,
num_points3D, num_observations, mean_track_length, mean_reprojection_error (pycolmap's, from the
stored ERROR values), recomputed_mean_reprojection_error, mean_observation_reprojection_error,
max_reprojection_error, behind_camera_observations, short_tracks, max_stored_error_mismatch,
cameras (id, model,
width, height, params), images (id, name, camera_id, num_points2D, num_points3D), ok.

Exit status: 0 when the model was read and every check passed; 1 when a check failed (the JSON is
still printed, with `ok: false` and `errors`); 2 when pycolmap is missing, DIR does not exist or
pycolmap cannot read the model (message on stderr). Needs `pycolmap` (tested with 4.2.1) and
numpy.
"""

import json
import math
import os
import sys

MAX_LISTED_ERRORS = 20
STORED_ERROR_TOLERANCE = 1e-3


def resolve(path):
    for cand in (path, os.path.join(path, "0"), os.path.join(path, "sparse", "0")):
        if any(os.path.isfile(os.path.join(cand, f)) for f in ("cameras.bin", "cameras.txt")):
            return cand
    return None


def finite(values):
    return all(math.isfinite(float(v)) for v in values)


def main(argv):
    args = [a for a in argv[1:] if not a.startswith("--")]
    flags = {a for a in argv[1:] if a.startswith("--")}
    if len(args) != 1 or flags - {"--skip-error-check"}:
        print(__doc__.strip(), file=sys.stderr)
        return 2
    check_errors = "--skip-error-check" not in flags
    try:
        import numpy as np
        import pycolmap
    except ImportError as e:  # pragma: no cover - environment dependent
        print(f"check_colmap_model.py: cannot import pycolmap/numpy: {e} (pip install pycolmap==4.2.1)", file=sys.stderr)
        return 2
    model_dir = resolve(args[0])
    if model_dir is None:
        print(f"check_colmap_model.py: {args[0]}: no COLMAP model (cameras.bin / cameras.txt) here or in sparse/0", file=sys.stderr)
        return 2
    try:
        rec = pycolmap.Reconstruction(model_dir)
    except Exception as e:  # pycolmap raises various types for malformed files
        print(f"check_colmap_model.py: {model_dir}: pycolmap cannot read the model: {e}", file=sys.stderr)
        return 2

    errors = []

    def fail(msg):
        if len(errors) < MAX_LISTED_ERRORS:
            errors.append(msg)
        elif len(errors) == MAX_LISTED_ERRORS:
            errors.append("... further errors omitted")

    cameras = []
    for cid, cam in sorted(rec.cameras.items()):
        params = [float(p) for p in cam.params]
        if not finite(params) or cam.width <= 0 or cam.height <= 0:
            fail(f"camera {cid}: non-finite parameters or empty size")
        cameras.append({"id": int(cid), "model": str(cam.model_name), "width": int(cam.width), "height": int(cam.height), "params": params})
    if rec.num_images() == 0:
        fail("the model has no image")

    images = []
    for iid, im in sorted(rec.images.items()):
        if im.camera_id not in rec.cameras:
            fail(f"image {iid}: unknown camera {im.camera_id}")
        if not im.has_pose:
            fail(f"image {iid}: no pose")
        else:
            pose = im.cam_from_world()
            if not (finite(pose.rotation.quat) and finite(pose.translation)):
                fail(f"image {iid}: non-finite pose")
        n3d = 0
        for idx, p2 in enumerate(im.points2D):
            if not finite(p2.xy):
                fail(f"image {iid} POINTS2D[{idx}]: non-finite xy")
            if p2.has_point3D():
                n3d += 1
                pid = p2.point3D_id
                if pid not in rec.points3D:
                    fail(f"image {iid} POINTS2D[{idx}]: POINT3D_ID {pid} does not exist")
                elif not any(e.image_id == iid and e.point2D_idx == idx for e in rec.points3D[pid].track.elements):
                    fail(f"image {iid} POINTS2D[{idx}]: point {pid}'s track lacks this observation")
        images.append({"id": int(iid), "name": im.name, "camera_id": int(im.camera_id), "num_points2D": len(im.points2D), "num_points3D": n3d})

    point_means = []
    obs_errors = []
    behind = 0
    mismatch = 0.0
    num_obs = 0
    short = 0
    for pid, p in rec.points3D.items():
        xyz = np.asarray(p.xyz, dtype=np.float64)
        if not finite(xyz):
            fail(f"point {pid}: non-finite xyz")
            continue
        elements = p.track.elements
        seen = set()
        errs = []
        any_behind = False
        for e in elements:
            num_obs += 1
            if e.image_id in seen:
                fail(f"point {pid}: two observations in image {e.image_id}")
            seen.add(e.image_id)
            if e.image_id not in rec.images:
                fail(f"point {pid}: track names unknown image {e.image_id}")
                continue
            im = rec.images[e.image_id]
            if e.point2D_idx >= len(im.points2D):
                fail(f"point {pid}: image {e.image_id} has no POINTS2D[{e.point2D_idx}]")
                continue
            p2 = im.points2D[e.point2D_idx]
            if not p2.has_point3D() or p2.point3D_id != pid:
                fail(f"point {pid}: image {e.image_id} POINTS2D[{e.point2D_idx}] does not point back")
            proj = im.project_point(xyz)
            if proj is None:
                behind += 1
                any_behind = True
                continue
            errs.append(float(np.linalg.norm(np.asarray(proj) - np.asarray(p2.xy))))
        if len(elements) < 2:
            short += 1
        obs_errors.extend(errs)
        if errs:
            mean = sum(errs) / len(errs)
            point_means.append(mean)
            if not any_behind and p.has_error():
                d = abs(mean - float(p.error))
                mismatch = max(mismatch, d)
                if check_errors and d > STORED_ERROR_TOLERANCE:
                    fail(f"point {pid}: stored ERROR {p.error} vs recomputed {mean}")

    if num_obs != rec.compute_num_observations():
        fail(f"track elements {num_obs} vs pycolmap's observation count {rec.compute_num_observations()}")

    def mean_or_none(v):
        return sum(v) / len(v) if v else None

    stored = rec.compute_mean_reprojection_error() if rec.num_points3D() else None
    out = {
        "pycolmap_version": getattr(pycolmap, "__version__", None),
        "path": model_dir,
        "num_cameras": rec.num_cameras(),
        "num_images": rec.num_images(),
        "num_reg_images": rec.num_reg_images(),
        "num_points3D": rec.num_points3D(),
        "num_observations": rec.compute_num_observations(),
        "mean_track_length": rec.compute_mean_track_length() if rec.num_points3D() else None,
        "mean_reprojection_error": stored,
        "recomputed_mean_reprojection_error": mean_or_none(point_means),
        "mean_observation_reprojection_error": mean_or_none(obs_errors),
        "max_reprojection_error": max(obs_errors) if obs_errors else None,
        "behind_camera_observations": behind,
        "short_tracks": short,
        "max_stored_error_mismatch": mismatch,
        "cameras": cameras,
        "images": images,
        "ok": not errors,
    }
    if errors:
        out["errors"] = errors
    print(json.dumps(out, indent=2))
    if errors:
        print(f"check_colmap_model.py: {model_dir}: {len(errors)} problem(s), first: {errors[0]}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
