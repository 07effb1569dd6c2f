import json

import numpy as np
import pytest

from calibration.camera import Camera, look_at_c2w
from calibration.capture import CaptureError, FrameData, load_views, read_capture, rig_metres_per_unit, write_capture
from tests.conftest import require_shared


def small_frames(n=3, w=40, h=30, dist=()):
    rng = np.random.default_rng(0)
    k = np.array([[50.0, 0, w / 2], [0, 50.0, h / 2], [0, 0, 1]])
    frames = []
    for i in range(n):
        ang = 2 * np.pi * i / n
        c2w = look_at_c2w(np.array([np.cos(ang), np.sin(ang), 0.3]), np.zeros(3))
        img = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        mask = np.zeros((h, w), bool)
        mask[5:20, 10:30] = True
        frames.append(FrameData(f"cam{i:02d}", img, Camera(k, w, h, np.array(dist, float), c2w), f"cam{i:02d}", 1000 + i, mask))
    return frames


def test_roundtrip_is_lossless_and_verified(tmp_path):
    frames = small_frames()
    cap = write_capture(
        tmp_path / "cap",
        frames,
        backgrounds={"cam00": frames[0].image},
        meta={"rig_id": "r1", "calibration_id": "c7", "trigger": {"seq": 4}},
    )
    assert len(cap) == 3 and cap.has_masks
    again = read_capture(tmp_path / "cap")
    for i, f in enumerate(frames):
        np.testing.assert_array_equal((again.image(i) * 255).round().astype(np.uint8), f.image)
        np.testing.assert_array_equal(again.mask(i), f.mask)
        np.testing.assert_allclose(again.frames[i].camera.c2w, f.camera.c2w, atol=1e-12)
        assert again.frames[i].camera_id == f.camera_id and again.frames[i].timestamp_ns == 1000 + i
    # No units given, none written: the scale of this rig frame is unknown.
    assert again.meta["calibration_id"] == "c7" and "units" not in again.meta
    assert set(again.meta["sha256"]) == {
        "images/cam00.png",
        "images/cam01.png",
        "images/cam02.png",
        "masks/cam00.png",
        "masks/cam01.png",
        "masks/cam02.png",
        "background/cam00.png",
    }
    np.testing.assert_array_equal((again.background("cam00") * 255).round().astype(np.uint8), frames[0].image)
    images, masks, cams = load_views(again, [2, 0])
    assert images.shape == (2, 30, 40, 3) and images.dtype == np.float32 and masks.shape == (2, 30, 40)
    # No temporary directories left behind.
    assert [p.name for p in tmp_path.iterdir()] == ["cap"]


def test_units_only_when_the_calibration_is_metric(tmp_path):
    metric = write_capture(tmp_path / "metric", small_frames(), meta={"units": "m"})
    assert metric.meta["units"] == "m" and rig_metres_per_unit(metric.meta) == 1.0
    assert rig_metres_per_unit({"units": "mm"}) == 1e-3
    unknown = write_capture(tmp_path / "sfm", small_frames())
    assert "units" not in unknown.meta and rig_metres_per_unit(unknown.meta) is None
    with pytest.raises(CaptureError, match="units 'furlong' is not one of m, mm, cm, in"):
        write_capture(tmp_path / "bad", small_frames(), meta={"units": "furlong"})
    assert not (tmp_path / "bad").exists()


def test_transforms_json_is_nerfstudio_compatible(tmp_path):
    write_capture(tmp_path / "cap", small_frames())
    doc = json.loads((tmp_path / "cap" / "transforms.json").read_text())
    f0 = doc["frames"][0]
    for key in ("file_path", "transform_matrix", "fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "p1", "p2", "camera_id", "timestamp_ns"):
        assert key in f0
    # nerfstudio's OpenGL c2w: the camera looks down its -z axis, towards the origin here.
    m = np.array(f0["transform_matrix"])
    forward = -m[:3, 2]
    np.testing.assert_allclose(forward, -m[:3, 3] / np.linalg.norm(m[:3, 3]), atol=1e-9)


def test_existing_capture_is_never_overwritten(tmp_path):
    write_capture(tmp_path / "cap", small_frames())
    with pytest.raises(CaptureError, match="never overwritten"):
        write_capture(tmp_path / "cap", small_frames())


def test_undistorted_at_load(tmp_path):
    cap = write_capture(tmp_path / "cap", small_frames(dist=(-0.2, 0.05, 0.0, 0.0)))
    assert not cap.frames[0].camera.is_pinhole
    assert cap.camera(0).is_pinhole
    raw = cap.image(0, undistort=False)
    assert not np.allclose(cap.image(0), raw)


def corrupt(tmp_path, how):
    root = tmp_path / "cap"
    write_capture(root, small_frames())
    doc = json.loads((root / "transforms.json").read_text())
    if how == "truncated":
        data = (root / "images/cam01.png").read_bytes()
        (root / "images/cam01.png").write_bytes(data[: len(data) // 2])
    elif how == "digest":
        doc["cadsplat"]["sha256"]["images/cam01.png"] = "0" * 64
    elif how == "missing":
        (root / "images/cam01.png").unlink()
    elif how == "nan":
        doc["frames"][1]["transform_matrix"][0][3] = float("nan")
    elif how == "nonrigid":
        doc["frames"][1]["transform_matrix"][0][0] *= 1.5
    elif how == "json":
        (root / "transforms.json").write_text("{ not json")
        return root
    elif how == "up":
        doc["cadsplat"]["up_rig"] = {"vector": [0, 0, 0], "source": "calibration"}
    (root / "transforms.json").write_text(json.dumps(doc))
    return root


@pytest.mark.parametrize(
    "how, pattern",
    [
        ("truncated", r"cam01\.png.*(sha256|truncated)"),
        ("digest", r"cam01\.png: sha256 does not match"),
        ("missing", r"1 image files are missing \(images/cam01\.png\)"),
        ("nan", r"frame 1 .*NaN"),
        ("nonrigid", r"frame 1 .*not rigid"),
        ("json", r"transforms\.json: invalid JSON"),
        ("up", r"cadsplat\.up_rig\.vector"),
    ],
)
def test_bad_input_is_one_sentence_naming_file_and_problem(tmp_path, how, pattern):
    root = corrupt(tmp_path, how)
    with pytest.raises(CaptureError, match=pattern) as err:
        read_capture(root)
    assert "\n" not in str(err.value)


def test_truncated_png_is_caught_at_decode_without_manifest(tmp_path):
    root = corrupt(tmp_path, "truncated")
    cap = read_capture(root, verify=False)
    with pytest.raises(CaptureError, match=r"cam01\.png: PNG is truncated"):
        cap.image(1)


def test_blender_nerf_synthetic_variant(tmp_path):
    frames = small_frames(n=2)
    write_capture(tmp_path / "cap", frames)
    doc = {
        "camera_angle_x": 2 * np.arctan(20 / 50.0),
        "frames": [
            {
                "file_path": "./images/cam00",
                "transform_matrix": json.loads((tmp_path / "cap/transforms.json").read_text())["frames"][0]["transform_matrix"],
            }
        ],
    }
    (tmp_path / "cap/transforms.json").write_text(json.dumps(doc))
    cap = read_capture(tmp_path / "cap")
    cam = cap.frames[0].camera
    assert (cam.width, cam.height) == (40, 30)
    np.testing.assert_allclose(cam.K, [[50, 0, 20], [0, 50, 15], [0, 0, 1]], atol=1e-9)
    np.testing.assert_allclose(cam.c2w, frames[0].camera.c2w, atol=1e-12)


def test_real_instant_ngp_fox_capture(tmp_path):
    fox = require_shared("real", "fox")
    with pytest.raises(CaptureError, match=r"lists 67 frames but 17 image files are missing"):
        read_capture(fox)
    cap = read_capture(fox, allow_missing=True)
    assert len(cap) == 50 and len(cap.missing) == 17
    doc = json.loads((fox / "transforms.json").read_text())
    cam = cap.frames[0].camera
    np.testing.assert_allclose(cam.K, [[doc["fl_x"], 0, doc["cx"]], [0, doc["fl_y"], doc["cy"]], [0, 0, 1]])
    np.testing.assert_allclose(cam.dist, [doc["k1"], doc["k2"], doc["p1"], doc["p2"]])
    assert (cam.width, cam.height) == (1080, 1920)
    # A point on the optical axis projects to the principal point; an off-axis point follows the
    # file's distortion model exactly (compared against a direct evaluation of it).
    gl = np.array(doc["frames"][0]["transform_matrix"])
    centre, forward = gl[:3, 3], -gl[:3, 2]
    uv, depth = cam.project(centre + 2.0 * forward)
    np.testing.assert_allclose(uv[0], [doc["cx"], doc["cy"]], atol=1e-6)
    right, up = gl[:3, 0], gl[:3, 1]
    x, y = 0.2, -0.3  # normalised OpenCV coordinates (y down = -up)
    uv, _ = cam.project(centre + forward + x * right - y * up)
    r2 = x * x + y * y
    radial = 1 + doc["k1"] * r2 + doc["k2"] * r2 * r2
    xd = x * radial + 2 * doc["p1"] * x * y + doc["p2"] * (r2 + 2 * x * x)
    yd = y * radial + doc["p1"] * (r2 + 2 * y * y) + 2 * doc["p2"] * x * y
    np.testing.assert_allclose(uv[0], [doc["fl_x"] * xd + doc["cx"], doc["fl_y"] * yd + doc["cy"]], atol=1e-6)
    img = cap.image(0, undistort=False)
    assert img.shape == (1920, 1080, 3)


def test_views_of_different_sizes_share_a_canvas_top_left(tmp_path):
    """A portrait photo among landscape ones: each view sits top-left on the largest canvas, so its K
    holds, and its camera crops its own pixels back."""
    frames = small_frames(2) + small_frames(1, w=30, h=40)
    frames[2] = FrameData("cam09", frames[2].image, frames[2].camera, "cam09", 2000, frames[2].mask)
    cap = write_capture(tmp_path / "cap", frames)
    assert load_views(cap, [0, 1])[0].shape == (2, 30, 40, 3)
    images, masks, cams = load_views(cap)
    assert images.shape == (3, 40, 40, 3) and masks.shape == (3, 40, 40)
    for i, cam in enumerate(cams):
        image, mask = cap.view(i)
        np.testing.assert_array_equal(cam.crop(images[i]), image)
        np.testing.assert_array_equal(cam.crop(masks[i]), mask)
        assert np.count_nonzero(images[i]) == np.count_nonzero(image) and masks[i].sum() == mask.sum()


def _redirect(root, how, outside):
    """Point one path the capture names at `outside` (a copy of its image, so only containment can refuse it)."""
    doc = json.loads((root / "transforms.json").read_text())
    if how == "absolute":
        doc["frames"][1]["file_path"] = str(outside)
    elif how == "dotdot":
        doc["frames"][1]["file_path"] = f"../{outside.name}"
    elif how == "mask-dotdot":
        doc["frames"][1]["mask_path"] = f"../{outside.name}"
    elif how == "background-dotdot":
        doc["cadsplat"]["background"]["cam01"] = f"../{outside.name}"
    elif how == "manifest-dotdot":
        doc["cadsplat"]["sha256"][f"../{outside.name}"] = "0" * 64
    elif how == "symlink":
        (root / "images/cam01.png").unlink()
        (root / "images/cam01.png").symlink_to(outside)
    (root / "transforms.json").write_text(json.dumps(doc))


@pytest.mark.parametrize("how", ["absolute", "dotdot", "mask-dotdot", "background-dotdot", "manifest-dotdot", "symlink"])
def test_paths_a_capture_names_stay_inside_it(tmp_path, how):
    """Issue 58 (3): a capture's file_path, mask_path, background and manifest paths never read outside its folder."""
    frames = small_frames()
    root = tmp_path / "cap"
    write_capture(root, frames, backgrounds={"cam01": frames[1].image})
    outside = tmp_path / "secret.png"
    outside.write_bytes((root / "images/cam01.png").read_bytes())
    _redirect(root, how, outside)
    with pytest.raises(CaptureError, match=r"leads outside|is absolute") as err:
        read_capture(root, verify=False) if how != "manifest-dotdot" else read_capture(root)
    assert "\n" not in str(err.value) and "transforms.json" in str(err.value)


def png_bomb(path, width: int, height: int) -> int:
    """Write an all-black RGB PNG of width x height, streamed through zlib so the canvas is never in memory; returns its size in bytes."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    z, row, idat = zlib.compressobj(9), b"\0" * (1 + 3 * width), []
    for _ in range(height):
        idat.append(z.compress(row))
    idat.append(z.flush())
    data = (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
        + chunk(b"IDAT", b"".join(idat))
        + chunk(b"IEND", b"")
    )
    path.write_bytes(data)
    return len(data)


def test_a_png_bomb_is_refused_from_its_header_without_decoding(tmp_path, monkeypatch):
    """Issue 58 (9): a few-hundred-KB PNG declaring 12000x12000 is refused in one sentence before any pixel is decoded."""
    import cv2

    root = tmp_path / "cap"
    write_capture(root, small_frames())
    size = png_bomb(root / "images/cam01.png", 12000, 12000)
    assert size < 1 << 20
    doc = json.loads((root / "transforms.json").read_text())
    for key in ("w", "h"):
        doc["frames"][1].pop(key)  # the size is read from the header, as for a nerfstudio capture that states none
    (root / "transforms.json").write_text(json.dumps(doc))

    def no_decoding(*_a, **_k):
        raise AssertionError("the bomb was decoded")

    monkeypatch.setattr(cv2, "imdecode", no_decoding)
    with pytest.raises(CaptureError, match=r"cam01\.png: image declares 12000x12000 pixels \(144 MP\), above the cap of 50 MP") as err:
        read_capture(root, verify=False)
    assert "\n" not in str(err.value)
    doc["frames"][1].update(w=12000, h=12000)
    (root / "transforms.json").write_text(json.dumps(doc))
    cap = read_capture(root, verify=False)
    with pytest.raises(CaptureError, match=r"cam01\.png: image declares 12000x12000 pixels .*it was not decoded"):
        cap.view(1)
    with pytest.raises(CaptureError, match=r"above the cap of 0\.001 MP"):
        read_capture(root, verify=False, max_pixels=1000).image(0)
