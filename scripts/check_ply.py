#!/usr/bin/env python3
"""Opens a binary PLY point cloud with `plyfile` and prints a JSON summary.

Usage: python3 scripts/check_ply.py FILE [--allow-ascii] [--allow-empty]

Meant for the clouds ggpt-rs writes (`ggpt_core::io::ply::write_ply`, `formats.md` §6.1: binary
little-endian, `element vertex n`, `float x y z`, `uchar red green blue`, optional
`float confidence`), e.g. `ggpt_points.ply`, `ff_points.ply`, `sfm_points.ply` of `ggpt-infer`.

Printed JSON (stdout):

    {"plyfile_version", "path", "format" ("binary_little_endian" | "binary_big_endian" | "ascii"),
     "comments", "elements": [{"name", "count"}], "vertex_count",
     "properties": [{"name", "type"}]   (vertex properties in file order; numpy dtype, e.g. "f4"),
     "has_color", "has_confidence",
     "xyz_min": [x, y, z], "xyz_max": [x, y, z]   (null when there is no vertex),
     "confidence_min", "confidence_max"           (null without confidence or vertices),
     "ok", "errors" (only when not ok)}

Exit status 0 when every check passes; 1 when the file was parsed but a check failed (JSON still
printed, `ok: false`); 2 when plyfile / numpy is missing or the file cannot be opened or parsed
(message on stderr). Checks: the format is binary little-endian (ASCII only with
--allow-ascii; big-endian is rejected, as by the project's reader), a `vertex`
element exists with float `x y z` (f4/f8) that are all finite, `red green blue` are present and
`u1` when present together (all three or none), a `confidence` property is float and finite,
there is at least one vertex (unless --allow-empty), and a binary file holds exactly header +
records (no trailing bytes). plyfile reads the whole body, so a truncated file fails to parse
(exit 2). Tested with plyfile 1.1.5 / numpy 2.4.
"""

import json
import sys


def package_version(name):
    try:
        from importlib.metadata import version

        return version(name)
    except Exception:
        return None


def expected_binary_size(path, ply):
    """Header bytes + records of a binary PLY with scalar properties only; None otherwise."""
    import numpy as np
    import plyfile

    with open(path, "rb") as f:
        head = f.read(1 << 16)
    end = head.find(b"end_header")
    if end < 0:
        return None
    nl = head.find(b"\n", end)
    if nl < 0:
        return None
    size = nl + 1
    for el in ply.elements:
        if any(isinstance(p, plyfile.PlyListProperty) for p in el.properties):
            return None
        size += int(el.count) * sum(np.dtype(p.val_dtype).itemsize for p in el.properties)
    return size


def main(argv):
    args = [a for a in argv[1:] if not a.startswith("--")]
    flags = {a for a in argv[1:] if a.startswith("--")}
    unknown = flags - {"--allow-ascii", "--allow-empty"}
    if len(args) != 1 or unknown or "--help" in flags:
        print(__doc__.strip(), file=sys.stderr)
        return 2
    path = args[0]
    try:
        import numpy as np
        import plyfile
    except ImportError as e:  # environment dependent
        print(f"check_ply.py: cannot import plyfile/numpy: {e} (pip install plyfile==1.1.5)", file=sys.stderr)
        return 2
    try:
        ply = plyfile.PlyData.read(path)
    except Exception as e:  # plyfile raises PlyParseError, OSError, ValueError, ...
        print(f"check_ply.py: {path}: cannot read the PLY: {type(e).__name__}: {e}", file=sys.stderr)
        return 2

    errors = []
    if ply.text:
        fmt = "ascii"
    elif ply.byte_order == ">" or (ply.byte_order == "=" and sys.byteorder == "big"):
        fmt = "binary_big_endian"
    else:
        fmt = "binary_little_endian"
    if fmt == "ascii" and "--allow-ascii" not in flags:
        errors.append("ASCII PLY (ggpt-rs writes binary little-endian; pass --allow-ascii to accept)")
    if fmt == "binary_big_endian":
        errors.append("big-endian PLY (ggpt-rs writes and reads binary little-endian only)")

    elements = [{"name": el.name, "count": int(el.count)} for el in ply.elements]
    out = {
        "plyfile_version": package_version("plyfile"),
        "path": path,
        "format": fmt,
        "comments": list(ply.comments),
        "elements": elements,
        "vertex_count": 0,
        "properties": [],
        "has_color": False,
        "has_confidence": False,
        "xyz_min": None,
        "xyz_max": None,
        "confidence_min": None,
        "confidence_max": None,
    }
    if not ply.text:
        import os

        want = expected_binary_size(path, ply)
        have = os.path.getsize(path)
        if want is not None and have != want:
            errors.append(f"file has {have} bytes, header + records need {want} ({'trailing bytes' if have > want else 'truncated'})")
    names = [el.name for el in ply.elements]
    if "vertex" not in names:
        errors.append(f"no 'vertex' element (elements: {names})")
    else:
        v = ply["vertex"]
        data = v.data
        props = []
        for p in v.properties:
            if isinstance(p, plyfile.PlyListProperty):
                props.append({"name": p.name, "type": f"list {p.len_dtype} {p.val_dtype}"})
            else:
                props.append({"name": p.name, "type": str(np.dtype(data.dtype[p.name]).str.lstrip("<>|="))})
        types = {p["name"]: p["type"] for p in props}
        n = int(v.count)
        out["vertex_count"] = n
        out["properties"] = props
        for a in ("x", "y", "z"):
            if a not in types:
                errors.append(f"vertex property '{a}' missing")
            elif types[a] not in ("f4", "f8"):
                errors.append(f"vertex property '{a}' has type {types[a]}, expected float")
        colors = [c for c in ("red", "green", "blue") if c in types]
        if colors and len(colors) != 3:
            errors.append(f"incomplete colour: only {colors}")
        out["has_color"] = len(colors) == 3
        for c in colors:
            if types[c] != "u1":
                errors.append(f"vertex property '{c}' has type {types[c]}, expected uchar (u1)")
        if n == 0 and "--allow-empty" not in flags:
            errors.append("no vertex (pass --allow-empty to accept)")
        if all(a in types and types[a] in ("f4", "f8") for a in ("x", "y", "z")) and n > 0:
            xyz = np.stack([np.asarray(data[a], dtype=np.float64) for a in ("x", "y", "z")], axis=1)
            bad = ~np.isfinite(xyz).all(axis=1)
            if bad.any():
                errors.append(f"{int(bad.sum())} vertices with non-finite coordinates (first: {int(np.argmax(bad))})")
            good = xyz[~bad]
            if len(good):
                out["xyz_min"] = [float(x) for x in good.min(axis=0)]
                out["xyz_max"] = [float(x) for x in good.max(axis=0)]
        if "confidence" in types:
            out["has_confidence"] = True
            if types["confidence"] not in ("f4", "f8"):
                errors.append(f"vertex property 'confidence' has type {types['confidence']}, expected float")
            elif n > 0:
                conf = np.asarray(data["confidence"], dtype=np.float64)
                if not np.isfinite(conf).all():
                    errors.append(f"{int((~np.isfinite(conf)).sum())} non-finite confidences")
                finite = conf[np.isfinite(conf)]
                if len(finite):
                    out["confidence_min"] = float(finite.min())
                    out["confidence_max"] = float(finite.max())

    out["ok"] = not errors
    if errors:
        out["errors"] = errors
    print(json.dumps(out, indent=2, allow_nan=False))
    if errors:
        print(f"check_ply.py: {path}: {len(errors)} problem(s), first: {errors[0]}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
