"""The feed-forward readers (`FeedForward.from_vggt`, `from_mapanything`, `from_pi3`, the
generic constructor) on arrays built from a synthetic scene, against the scene's own input."""

from __future__ import annotations

import numpy as np
import pytest

import ggpt_rs as ggpt


class FakeTensor:
    """Quacks like a torch tensor (`.detach().cpu().numpy()`), without torch."""

    def __init__(self, a: np.ndarray) -> None:
        self._a = a

    def detach(self) -> "FakeTensor":
        return self

    def cpu(self) -> "FakeTensor":
        return self

    def numpy(self) -> np.ndarray:
        return self._a


def camera_frame(points: np.ndarray, cam_from_world: np.ndarray) -> np.ndarray:
    """`[N, h, w, 3]` world points in each view's camera frame (float64)."""
    r, t = cam_from_world[:, :, :3], cam_from_world[:, :, 3]
    return np.einsum("nij,nhwj->nhwi", r, points.astype(np.float64)) + t[:, None, None, :]


def unproject(depth: np.ndarray, k: np.ndarray, cam_from_world: np.ndarray) -> np.ndarray:
    """VGGT's `unproject_depth_map_to_point_map`, in numpy (pixel centres at integers)."""
    n, h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    fx, fy, cx, cy = k[:, 0, 0], k[:, 1, 1], k[:, 0, 2], k[:, 1, 2]
    z = depth.astype(np.float64)
    cam = np.stack(
        [(u - cx[:, None, None]) / fx[:, None, None] * z, (v - cy[:, None, None]) / fy[:, None, None] * z, z],
        axis=-1,
    )
    r, t = cam_from_world[:, :, :3], cam_from_world[:, :, 3]
    return np.einsum("nji,nhwj->nhwi", r, cam - t[:, None, None, :])


@pytest.fixture(scope="module")
def ff(synth_scene):
    return ggpt.read_scene(synth_scene).ff


def vggt_dict(ff, batch: bool = True, float64: bool = False):
    e, k = ff.cam_from_world, ff.K
    depth = camera_frame(ff.points, e)[..., 2:3].astype(np.float32)
    images = np.transpose(ff.images, (0, 3, 1, 2))
    d = {
        "extrinsic": e if float64 else e.astype(np.float32),
        "intrinsic": k if float64 else k.astype(np.float32),
        "world_points": ff.points,
        "world_points_conf": ff.conf,
        "depth": depth,
        "depth_conf": ff.conf + 1.0,
        "images": images,
        "pose_enc": np.zeros((ff.num_views, 9), np.float32),
        "image_names": ["a.png"] * ff.num_views,
    }
    if batch:
        d = {key: (v[None] if isinstance(v, np.ndarray) else v) for key, v in d.items()}
    return d


def test_vggt_points_branch_equals_the_scene(ff):
    got = ggpt.FeedForward.from_vggt(vggt_dict(ff, float64=True), branch="points")
    assert got.format == "vggt" and got.num_views == ff.num_views
    assert np.array_equal(got.points, ff.points)
    assert np.array_equal(got.conf, ff.conf)
    assert np.array_equal(got.cam_from_world, ff.cam_from_world)
    assert np.array_equal(got.K, ff.K)
    assert np.array_equal(got.images, ff.images)


def test_vggt_depth_branch_unprojects_with_the_cameras(ff):
    d = vggt_dict(ff)
    got = ggpt.FeedForward.from_vggt(d)  # the official demo's default: depth
    want = unproject(d["depth"][0, ..., 0], d["intrinsic"][0].astype(np.float64), d["extrinsic"][0].astype(np.float64))
    assert float(np.abs(got.points - want).max()) <= 1e-5 * float(np.abs(want).max())
    assert np.array_equal(got.conf, ff.conf + 1.0)
    # the unprojected depth of the scene's own points lies on the pixel rays of its cameras
    assert got.points.shape == ff.points.shape


def test_vggt_npz_and_torch_tensors(ff, tmp_path):
    d = vggt_dict(ff)
    arrays = {k: v for k, v in d.items() if isinstance(v, np.ndarray)}
    np.savez(tmp_path / "predictions.npz", **arrays)
    a = ggpt.FeedForward.from_vggt(np.load(tmp_path / "predictions.npz"))
    b = ggpt.FeedForward.from_vggt({k: FakeTensor(v) for k, v in arrays.items()})
    c = ggpt.FeedForward.from_arrays(arrays)  # detected from the keys
    assert np.array_equal(a.points, b.points) and np.array_equal(a.points, c.points)
    assert c.format == "vggt"


def test_generic_mapanything_and_pi3(ff):
    g = ggpt.FeedForward(ff.points.astype(np.float64), ff.conf, ff.cam_from_world, ff.K, ff.images)
    assert np.array_equal(g.points, ff.points) and g.format == "ggpt"
    # MapAnything: per-view dicts with camera-to-world poses
    poses = np.tile(np.eye(4), (ff.num_views, 1, 1))
    r, t = ff.cam_from_world[:, :, :3], ff.cam_from_world[:, :, 3]
    poses[:, :3, :3] = np.transpose(r, (0, 2, 1))
    poses[:, :3, 3] = -np.einsum("nji,nj->ni", r, t)
    views = [
        {
            "pts3d": ff.points[v][None],
            "conf": ff.conf[v][None],
            "intrinsics": ff.K[v][None],
            "camera_poses": poses[v][None],
            "img_no_norm": ff.images[v][None],
        }
        for v in range(ff.num_views)
    ]
    ma = ggpt.FeedForward.from_mapanything(views)
    assert ma.format == "mapanything" and np.array_equal(ma.points, ff.points)
    np.testing.assert_allclose(ma.cam_from_world, ff.cam_from_world, atol=1e-12)
    # Pi3: world points, confidence logits, poses; intrinsics estimated from camera-frame points
    # on the rays of a pinhole camera with Pi3's principal point (w/2, h/2)
    k = ff.K.copy()
    k[:, 0, 2], k[:, 1, 2] = ff.width / 2, ff.height / 2
    k[:, 1, 1] = k[:, 0, 0]  # one focal per view, as the estimate
    depth = camera_frame(ff.points, ff.cam_from_world)[..., 2]
    identity = np.tile(np.eye(3, 4), (ff.num_views, 1, 1))
    local = unproject(depth, k, identity).astype(np.float32)
    pi3 = ggpt.FeedForward.from_pi3(
        {"points": ff.points[None], "local_points": local[None], "conf": np.zeros_like(ff.conf)[None, ..., None], "camera_poses": poses[None]}
    )
    assert pi3.format == "pi3" and np.allclose(pi3.conf, 2.0)
    f = pi3.K[:, 0, 0]
    assert np.all(np.abs(f - k[:, 0, 0]) < 1e-3 * k[:, 0, 0]), (f, k[:, 0, 0])
    assert np.array_equal(pi3.K[:, 0, 2], k[:, 0, 2])
    given = ggpt.FeedForward.from_pi3({"points": ff.points, "conf": ff.conf, "camera_poses": poses}, K=ff.K)
    assert np.array_equal(given.K, ff.K)


def test_bad_feed_forward_arrays(ff):
    with pytest.raises(ggpt.FormatError) as e:
        ggpt.FeedForward.from_arrays({"foo": np.zeros(3, np.float32)})
    assert "foo" in str(e.value) and "VGGT" in str(e.value)
    d = vggt_dict(ff, batch=False)
    del d["depth"]
    with pytest.raises(ggpt.FormatError) as e:
        ggpt.FeedForward.from_vggt(d)
    assert e.value.key == "depth" and "points" in str(e.value)
    d = vggt_dict(ff, batch=False)
    d["extrinsic"] = np.stack([d["extrinsic"]] * 2)
    with pytest.raises(ggpt.InvalidInputError) as e:
        ggpt.FeedForward.from_vggt(d)
    assert "extrinsic" in str(e.value)
    pts = ff.points.copy()
    pts.reshape(-1)[7] = np.nan
    with pytest.raises(ggpt.NonFiniteError) as e:
        ggpt.FeedForward(pts, ff.conf, ff.cam_from_world, ff.K)
    assert e.value.array == "points" and e.value.index == 7
    with pytest.raises(ggpt.InvalidInputError) as e:
        ggpt.FeedForward(ff.points, ff.conf[:, :-1], ff.cam_from_world, ff.K)
    assert "conf" in str(e.value)
    with pytest.raises(ggpt.InvalidInputError):
        ggpt.FeedForward(ff.points.astype(np.int32), ff.conf, ff.cam_from_world, ff.K)
