#!/usr/bin/env python3
"""Export dense matches of RoMa v2 and/or UFM to the ggpt-sfm raw-matcher interchange layout.

Not run in CI. Requires torch, safetensors and the matcher packages (romav2, uniflowmatch); the
matcher calls below are the ones the official GGPT `matching/densematcher.py` makes.

Interchange layout (one safetensors file, see docs/sfm.md), for N views at ff resolution h x w:

  m{i}_warp          F32 [N, N, Hm, Wm, 2]  RoMa-style: [s, t] = normalised EDGE coordinates in
                                             view t (-1/+1 = outer image border) of every matcher
                                             pixel of view s, at the matcher resolution Hm x Wm
  m{i}_overlap       F32 [N, N, Hm, Wm]     RoMa overlap / certainty in [0, 1]
  m{i}_flow          F32 [N, N, 2, Ho, Wo]  UFM-style: flow (dx, dy) in OUTPUT pixels, location in
                                             t of pixel (x, y) of s = (x + dx, y + dy)
  m{i}_covisibility  F32 [N, N, Ho, Wo]     UFM covisibility in [0, 1]
  m{i}_pixwarp       F32 [N, N, Hm, Wm, 2]  generic: target location in matcher PIXELS (pixel centre)
  m{i}_score         F32 [N, N, Hm, Wm]     generic score
  sp_scores          F32 [N, h*w]           optional BA ranking score per ff pixel (e.g. SuperPoint)
  hr_size            I64 [2]                optional (H, W) of the images given to the matchers

Matchers are numbered i = 0, 1, ... in ensembling order (ties go to the lower index). Diagonal
entries (s == t) are ignored (fill with zeros). Missing pairs: zeros (score 0 -> invalid).

Usage:
  python scripts/export_matches.py --images IMG_DIR --ff-size 518x392 --out matches.safetensors \
      [--roma base|fast] [--ufm refine|base]
"""

import argparse
import glob
import os

import numpy as np


def load_images(folder):
    from PIL import Image

    paths = sorted(p for p in glob.glob(os.path.join(folder, "*")) if p.lower().endswith((".jpg", ".jpeg", ".png")))
    if len(paths) < 2:
        raise SystemExit(f"{folder}: need at least two images")
    return paths, [Image.open(p).convert("RGB") for p in paths]


def roma_v2(paths, variant):
    """RoMa v2: one symmetric call per unordered pair gives warp_AB/BA and overlap_AB/BA."""
    import torch
    from romav2 import RoMaV2  # official package name of RoMa v2

    model = RoMaV2(setting=variant).eval()
    n = len(paths)
    warps, overlaps = None, None
    with torch.inference_mode():
        for a in range(n):
            for b in range(a + 1, n):
                out = model.match(paths[a], paths[b])
                for (s, t, wk, ok) in ((a, b, "warp_AB", "overlap_AB"), (b, a, "warp_BA", "overlap_BA")):
                    warp = out[wk][0].float().cpu().numpy()  # [Hm, Wm, 2], normalised edge coords
                    ov = out[ok][0].float().cpu().numpy().reshape(warp.shape[:2])
                    if warps is None:
                        hm, wm = warp.shape[:2]
                        warps = np.zeros((n, n, hm, wm, 2), np.float32)
                        overlaps = np.zeros((n, n, hm, wm), np.float32)
                    warps[s, t] = warp
                    overlaps[s, t] = ov
    return warps, overlaps


def ufm(images, variant, ff_w, ff_h):
    """UFM: one call per ordered pair, images resized to the ff resolution."""
    import torch
    from uniflowmatch.models.ufm import UniFlowMatchClassificationRefinement, UniFlowMatchConfidence

    cls = UniFlowMatchClassificationRefinement if variant == "refine" else UniFlowMatchConfidence
    model = cls.from_pretrained("infinity1096/UFM-Refine" if variant == "refine" else "infinity1096/UFM-Base").eval()
    n = len(images)
    ims = [torch.from_numpy(np.asarray(im.resize((ff_w, ff_h)))) for im in images]
    flows = np.zeros((n, n, 2, ff_h, ff_w), np.float32)
    cov = np.zeros((n, n, ff_h, ff_w), np.float32)
    with torch.inference_mode():
        for s in range(n):
            for t in range(n):
                if s == t:
                    continue
                res = model.predict_correspondences_batched(source_image=ims[s], target_image=ims[t])
                flows[s, t] = res.flow.flow_output[0].float().cpu().numpy()
                cov[s, t] = res.covisibility.mask[0].float().cpu().numpy()
    return flows, cov


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", required=True, help="folder of images (lexicographic order = view order)")
    ap.add_argument("--ff-size", required=True, help="feed-forward resolution WxH, e.g. 518x392")
    ap.add_argument("--out", required=True)
    ap.add_argument("--roma", choices=["base", "fast"], default="base", help="RoMa v2 setting (matcher 0)")
    ap.add_argument("--ufm", choices=["refine", "base", "none"], default="none", help="add UFM as matcher 1")
    args = ap.parse_args()
    from PIL import Image  # noqa: F401  (fail early when missing)
    from safetensors.numpy import save_file

    ff_w, ff_h = (int(v) for v in args.ff_size.lower().split("x"))
    paths, images = load_images(args.images)
    tensors = {}
    warps, overlaps = roma_v2(paths, args.roma)
    tensors["m0_warp"], tensors["m0_overlap"] = warps, overlaps
    if args.ufm != "none":
        flows, cov = ufm(images, args.ufm, ff_w, ff_h)
        tensors["m1_flow"], tensors["m1_covisibility"] = flows, cov
    tensors["hr_size"] = np.array([images[0].height, images[0].width], np.int64)
    save_file({k: np.ascontiguousarray(v) for k, v in tensors.items()}, args.out, metadata={"format": "ggpt-sfm-raw-matches"})
    print(f"wrote {args.out}: " + ", ".join(f"{k} {list(v.shape)}" for k, v in tensors.items()))


if __name__ == "__main__":
    main()
