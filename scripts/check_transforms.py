#!/usr/bin/env python3
"""Checks a splat-ready output folder: nerfstudio's `transforms.json` against the COLMAP model
beside it, read with pycolmap, and prints a JSON summary.

Usage: python3 scripts/check_transforms.py OUT

OUT holds `transforms.json`, `sparse/0/` and `images/` (`ggpt-infer run --out OUT`). For every
frame: the image named by `file_path` exists under OUT and is an image of the model with that
name; `w`, `h`, `fl_x`, `fl_y`, `cx`, `cy` equal its camera's width, height and PINHOLE /
SIMPLE_PINHOLE parameters; `transform_matrix` equals the camera-to-world of its pose
(`pycolmap` cam_from_world inverted) with the camera's y and z axes negated (OpenCV -> OpenGL),
to 1e-6. Prints `ok`, `frames`, `max_pose_difference`, `max_intrinsics_difference`, `names`,
`sizes` and `errors`; exit 0 when every check passed, 1 otherwise, 2 when pycolmap is missing or
the files cannot be read. Needs `pycolmap` (tested with 4.2.1) and numpy.
"""

import json
import os
import sys

TOLERANCE = 1e-6


def main(argv):
    if len(argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    out = argv[1]
    try:
        import numpy as np
        import pycolmap
    except ImportError as e:
        print(f"needs numpy and pycolmap: {e}", file=sys.stderr)
        return 2
    try:
        with open(os.path.join(out, "transforms.json")) as f:
            t = json.load(f)
        rec = pycolmap.Reconstruction(os.path.join(out, "sparse", "0"))
    except Exception as e:  # noqa: BLE001 - report any reader failure
        print(f"cannot read {out}: {e}", file=sys.stderr)
        return 2
    by_name = {im.name: im for im in rec.images.values()}
    errors, names, sizes = [], [], []
    max_pose = max_k = 0.0
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    for frame in t["frames"]:
        name = os.path.basename(frame["file_path"])
        names.append(name)
        if not os.path.isfile(os.path.join(out, frame["file_path"])):
            errors.append(f"{frame['file_path']}: no such file")
        im = by_name.get(name)
        if im is None:
            errors.append(f"{name}: not an image of the COLMAP model")
            continue
        cam = rec.cameras[im.camera_id]
        sizes.append([cam.width, cam.height])
        p = list(cam.params)
        fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if len(p) == 3 else p[:4]
        for key, want in (("fl_x", fx), ("fl_y", fy), ("cx", cx), ("cy", cy), ("w", cam.width), ("h", cam.height)):
            d = abs(float(frame[key]) - float(want))
            max_k = max(max_k, d)
            if d > TOLERANCE:
                errors.append(f"{name}: {key} {frame[key]} vs COLMAP {want}")
        w2c = np.eye(4)
        w2c[:3, :] = im.cam_from_world().matrix()
        c2w_gl = np.linalg.inv(w2c) @ flip
        d = float(np.abs(np.array(frame["transform_matrix"]) - c2w_gl).max())
        max_pose = max(max_pose, d)
        if d > TOLERANCE:
            errors.append(f"{name}: transform_matrix differs by {d}")
    if len(t["frames"]) != len(rec.images):
        errors.append(f"{len(t['frames'])} frames for {len(rec.images)} COLMAP images")
    summary = {
        "ok": not errors,
        "frames": len(t["frames"]),
        "max_pose_difference": max_pose,
        "max_intrinsics_difference": max_k,
        "names": names,
        "sizes": sizes,
        "ply_file_path": t.get("ply_file_path"),
        "errors": errors[:20],
    }
    print(json.dumps(summary))
    return 0 if not errors else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv))
