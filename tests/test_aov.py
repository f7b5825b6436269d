"""usdml.aov: AOV registry, EXR round-trips and header conventions, atomic writes, PNG previews,
usdrecord's frame naming and FrameSpec parsing."""

from __future__ import annotations

import json
import os

import numpy as np
import OpenEXR
import OpenImageIO as oiio
import pytest

from usdml.aov import exr as exr_mod
from usdml.aov import (
    AOVS, NO_ID, ExrError, FrameSpecError, OutputPathError, aov_for_render_var, camera_matrices,
    data_type_matches, format_frame, frame_placeholder, frame_spec, frame_spec_precision, get_aov,
    is_complete_exr, output_paths, read_exr, usdml_world_to_camera, usdml_world_to_ndc, write_exr,
    write_png_preview,
)
from usdml.errors import UsdmlError
from usdml.scene import Camera

H, W = 5, 7


def _all_aovs(rng) -> dict[str, np.ndarray]:
    out = {}
    for name, spec in AOVS.items():
        if spec.is_id:
            a = rng.integers(0, 1000, spec.shape(H, W)).astype(np.int64)
            a[0, 0] = -1
            a[0, 1] = NO_ID - 1         # largest id: exact only in a uint channel
            a[0, 2] = 2 ** 24 + 1       # not representable in float32
        else:
            a = rng.normal(size=spec.shape(H, W)).astype(np.float32) * 10
        out[name] = a
    out["depth"][1, 1] = np.inf
    return out


def _oiio_channels(path):
    inp = oiio.ImageInput.open(str(path))
    try:
        spec = inp.spec()
        return list(spec.channelnames), [str(t) for t in spec.channelformats] or [str(spec.format)] * spec.nchannels
    finally:
        inp.close()


# --- registry -----------------------------------------------------------------------------------

def test_registry_channels_and_types():
    assert AOVS["color"].channels() == ("R", "G", "B", "A")
    assert AOVS["depth"].channels() == ("Z",)
    assert AOVS["direct"].channels() == ("direct.R", "direct.G", "direct.B")
    assert AOVS["normal"].channels() == ("normal.X", "normal.Y", "normal.Z")
    assert AOVS["shadow"].channels() == ("shadow.Y",)
    assert AOVS["primId"].channels() == ("primId.id",)
    assert AOVS["direct"].channels("diffuse") == ("diffuse.R", "diffuse.G", "diffuse.B")
    assert AOVS["color"].channels("beauty") == ("R", "G", "B", "A")
    assert {a.pixel_type for a in AOVS.values() if a.name in ("color", "direct", "indirect", "albedo")} == {"half"}
    assert {AOVS[n].pixel_type for n in ("depth", "P", "Peye", "normal", "shadow", "lightCount")} == {"float"}
    assert AOVS["instanceId"].pixel_type == "uint"
    assert get_aov("cameraDepth") is AOVS["depth"] and get_aov("N") is AOVS["normal"]
    with pytest.raises(KeyError, match="unknown AOV"):
        get_aov("beautyy")
    assert AOVS["depth"].empty(2, 3)[0, 0] == np.inf
    assert AOVS["primId"].empty(2, 3).dtype == np.int64 and (AOVS["primId"].empty(2, 3) == -1).all()
    assert AOVS["color"].empty(2, 3).shape == (2, 3, 4)


@pytest.mark.parametrize("source, stype, aov", [
    ("color", "raw", "color"), ("Ci", "raw", "color"), ("depth", "raw", "depth"),
    ("cameraDepth", "raw", "depth"), ("z", "raw", "depth"), ("normal", "raw", "normal"),
    ("N", "raw", "normal"), ("Neye", "raw", "Neye"), ("P", "raw", "P"), ("Peye", "raw", "Peye"),
    ("primId", "raw", "primId"), ("instanceId", "intrinsic", "instanceId"),
    ("shadow", "raw", "shadow"), ("lightCount", "", "lightCount"),
    ("C.*", "lpe", "color"), ("C<RD>[<L.>O]", "lpe", "diffuse"), ("C<RS>L", "lpe", "specular"),
    ("CO", "lpe", "emission"), ("C <RD> .+ L", "lpe", "indirect"),
    ("lpe:C.*[<L.>O]", "raw", "color"),
])
def test_render_var_mapping(source, stype, aov):
    assert aov_for_render_var(source, stype).name == aov


@pytest.mark.parametrize("source, stype", [("st", "primvar"), ("displayColor", "primvar"),
                                           ("C<TS>L", "lpe"), ("bogus", "raw"), ("", "raw")])
def test_render_var_unknown_is_none(source, stype):
    assert aov_for_render_var(source, stype) is None


def test_data_type_matches():
    assert data_type_matches(AOVS["color"], "color3f") and data_type_matches(AOVS["color"], "color4f")
    assert data_type_matches(AOVS["depth"], "float") and not data_type_matches(AOVS["depth"], "color3f")
    assert data_type_matches(AOVS["primId"], "int") and not data_type_matches(AOVS["primId"], "float")
    assert data_type_matches(AOVS["normal"], "normal3f") and data_type_matches(AOVS["P"], None)


# --- EXR round trip -----------------------------------------------------------------------------

def test_exr_roundtrip_every_aov(tmp_path):
    rng = np.random.default_rng(1)
    aovs = _all_aovs(rng)
    path = write_exr(tmp_path / "f.0001.exr", aovs, timecode=1.0)
    assert path == tmp_path / "f.0001.exr" and is_complete_exr(path)

    names, types = _oiio_channels(path)
    expected = {c: a.pixel_type for a in AOVS.values() for c in a.channels()}
    assert sorted(names) == sorted(expected)
    assert names[:5] == ["R", "G", "B", "A", "Z"]          # how OIIO presents them
    assert dict(zip(names, types)) == expected              # half / float / uint per channel

    back, meta = read_exr(path)
    assert set(back) == set(AOVS)
    for name, spec in AOVS.items():
        got, want = back[name], aovs[name]
        assert got.shape == want.shape, name
        if spec.is_id:
            assert got.dtype == np.int64
            np.testing.assert_array_equal(got, want)        # exact, -1 restored
        else:
            assert got.dtype == spec.dtype, name
            np.testing.assert_array_equal(got, want.astype(spec.dtype))
    assert meta["compression"] == "zip"


def test_exr_orientation_row0_is_top(tmp_path):
    color = np.zeros((H, W, 4), np.float32)
    color[0, :, 0] = 1.0        # top row red
    color[:, 0, 1] = 1.0        # left column green
    path = write_exr(tmp_path / "o.exr", {"color": color})
    inp = oiio.ImageInput.open(str(path))
    px = inp.read_image(oiio.FLOAT)
    spec = inp.spec()
    inp.close()
    assert (spec.width, spec.height) == (W, H)
    assert (px[0, :, 0] == 1).all() and (px[1:, 1:, 0] == 0).all()
    assert (px[:, 0, 1] == 1).all() and (px[:, 1:, 1] == 0).all()
    np.testing.assert_array_equal(read_exr(path)[0]["color"], color)


def test_exr_renamed_layers_and_aliases(tmp_path):
    rgba = np.ones((H, W, 4), np.float32)
    diffuse = np.full((H, W, 3), 0.5, np.float32)
    path = write_exr(tmp_path / "r.exr",
                     {"beauty": rgba, "diffuse": diffuse, "cameraDepth": np.ones((H, W)), "N": np.zeros((H, W, 3))},
                     layers={"beauty": "color", "diffuse": "direct"})
    names, _ = _oiio_channels(path)
    assert set(names) == {"R", "G", "B", "A", "diffuse.R", "diffuse.G", "diffuse.B", "Z",
                          "N.X", "N.Y", "N.Z"}
    back, meta = read_exr(path)
    assert set(back) == {"beauty", "diffuse", "cameraDepth", "N"}
    assert back["diffuse"].shape == (H, W, 3) and back["beauty"].shape == (H, W, 4)
    assert json.loads(meta["usdml:aovs"])["diffuse"] == "direct"


@pytest.mark.parametrize("aovs, match", [
    ({"color": np.zeros((H, W, 3))}, r"shape \(H, W, 4\)"),
    ({"color": np.zeros((H, W, 4)), "depth": np.zeros((H + 1, W))}, "share a resolution"),
    ({"bogus": np.zeros((H, W))}, "unknown AOV"),
    ({"primId": np.full((H, W), -2)}, r"ids must lie in \[-1"),
    ({"primId": np.full((H, W), 0.5)}, "ids must be integers"),
    ({"color": np.zeros((H, W, 4)), "beauty": np.zeros((H, W, 4))}, "already written"),
    ({}, "no AOVs"),
])
def test_exr_rejects_bad_input(tmp_path, aovs, match):
    with pytest.raises(ValueError, match=match):
        write_exr(tmp_path / "bad.exr", aovs, layers={"beauty": "color"})
    assert os.listdir(tmp_path) == []


def test_exr_bad_compression_and_metadata(tmp_path):
    aovs = {"depth": np.zeros((H, W))}
    with pytest.raises(ValueError, match="unknown EXR compression"):
        write_exr(tmp_path / "a.exr", aovs, compression="lzma")
    with pytest.raises(ValueError, match="structural"):
        write_exr(tmp_path / "a.exr", aovs, metadata={"dataWindow": 1})
    with pytest.raises(TypeError, match="cannot store"):
        write_exr(tmp_path / "a.exr", aovs, metadata={"x": object()})
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("compression", ["none", "zips", "piz", "rle"])
def test_exr_lossless_compressions(tmp_path, compression):
    aovs = _all_aovs(np.random.default_rng(2))
    back, meta = read_exr(write_exr(tmp_path / "c.exr", aovs, compression=compression))
    assert meta["compression"] == compression
    np.testing.assert_array_equal(back["P"], aovs["P"])
    np.testing.assert_array_equal(back["primId"], aovs["primId"])


# --- header -------------------------------------------------------------------------------------

def _camera() -> Camera:
    # camera at (1, 2, 3), turned 30 degrees about +Y, looking down its -Z
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    xform = np.array([[c, 0, s, 1], [0, 1, 0, 2], [-s, 0, c, 3], [0, 0, 0, 1]], np.float64)
    return Camera(path="/cam", xform=xform, focal_length=35.0, horizontal_aperture=36.0,
                  vertical_aperture=24.0, clipping_range=(0.1, 100.0))


def test_exr_header_matrices_follow_openexr_convention(tmp_path):
    cam = _camera()
    w2c, w2ndc = camera_matrices(cam)
    path = write_exr(tmp_path / "m.exr", {"depth": np.ones((H, W))}, world_to_camera=w2c,
                     world_to_ndc=w2ndc, timecode=101.1)
    _, meta = read_exr(path)
    m_cam, m_ndc = meta["worldToCamera"], meta["worldToNDC"]
    assert m_cam.dtype == np.float32 and m_cam.shape == (4, 4)

    # a point 5 units in front of the camera, on its axis, then one at the top-right frustum corner
    ahead = cam.xform @ np.array([0.0, 0.0, -5.0, 1.0])
    p_cam = ahead @ m_cam.astype(np.float64)                    # row vector times matrix (Imath)
    np.testing.assert_allclose(p_cam[:3], [0, 0, 5], atol=1e-5)   # +z forward, in front => z > 0
    p = ahead @ m_ndc.astype(np.float64)
    np.testing.assert_allclose(p[:2] / p[3], [0.5, 0.5], atol=1e-6)
    half_w, half_h = 5 * 18 / 35, 5 * 12 / 35
    corner = cam.xform @ np.array([half_w, half_h, -5.0, 1.0])   # right, up in the image
    p = corner @ m_ndc.astype(np.float64)
    np.testing.assert_allclose(p[:2] / p[3], [1.0, 0.0], atol=1e-5)   # upper-right = (1, 0)
    right = cam.xform @ np.array([1.0, 0.0, -5.0, 1.0])
    assert (right @ m_cam.astype(np.float64))[0] > 0             # +x right

    # exact round trip in the documented convention (up to float32 storage)
    np.testing.assert_array_equal(m_cam, exr_mod.exr_world_to_camera(w2c))
    np.testing.assert_allclose(usdml_world_to_camera(m_cam), w2c, atol=1e-6)
    np.testing.assert_allclose(usdml_world_to_ndc(m_ndc), w2ndc, rtol=1e-6, atol=1e-6)
    f32 = np.random.default_rng(3).normal(size=(4, 4)).astype(np.float32)
    np.testing.assert_array_equal(exr_mod.exr_world_to_camera(usdml_world_to_camera(f32)), f32)

    # OpenImageIO sees the standard attributes as 4x4 matrices with the same values
    inp = oiio.ImageInput.open(str(path))
    attrs = {a.name: (str(a.type), a.value) for a in inp.spec().extra_attribs}
    inp.close()
    assert attrs["worldToCamera"][0] == "matrix"
    np.testing.assert_array_equal(np.array(attrs["worldToCamera"][1], np.float32).reshape(4, 4), m_cam)
    assert attrs["usdml:timeCode"] == ("double", 101.1)


def test_exr_header_usdml_metadata(tmp_path):
    settings = {"backend": "voxel", "resolution": [64, 64], "lights": 1000}
    path = write_exr(tmp_path / "h.exr", {"color": np.zeros((H, W, 4))}, timecode=-12.25,
                     stage="/shots/a.usda", settings=settings,
                     metadata={"usdml:backend": "voxel", "usdml:samples": 16, "usdml:scale": 0.1,
                               "usdml:big": 2 ** 40, "usdml:flag": True, "usdml:tags": ["a", "b"],
                               "usdml:extra": {"k": 1}, "usdml:v": np.array([1.0, 2.0, 3.0]),
                               "usdml:timeCode": 999.0, "skipped": None})
    _, meta = read_exr(path)
    assert meta["usdml:timeCode"] == -12.25                  # explicit argument wins
    assert meta["usdml:stage"] == "/shots/a.usda"
    assert json.loads(meta["usdml:settings"]) == settings
    assert meta["usdml:settings"] == json.dumps(settings, sort_keys=True)
    assert meta["usdml:backend"] == "voxel" and meta["usdml:samples"] == 16
    assert meta["usdml:scale"] == 0.1 and meta["usdml:big"] == 2 ** 40 and meta["usdml:flag"] == 1
    assert list(meta["usdml:tags"]) == ["a", "b"] and json.loads(meta["usdml:extra"]) == {"k": 1}
    np.testing.assert_array_equal(meta["usdml:v"], [1, 2, 3])
    assert "skipped" not in meta and "worldToCamera" not in meta
    assert "usdml:version" in meta


# --- atomic writes and completeness --------------------------------------------------------------

def _failing_writer(exc):
    """Stands in for ``OpenEXR.File`` when writing: leaves a partial file, then fails with ``exc``."""

    class FailingFile:
        def __init__(self, header, channels):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc_info):
            return False

        def write(self, path):
            with open(path, "wb") as f:          # a partial file under the temporary name
                f.write(b"\x76\x2f\x31\x01" + b"\0" * 100)
            raise exc

    return FailingFile


@pytest.mark.parametrize("exc", [RuntimeError("disk full"), KeyboardInterrupt()])
def test_exr_failed_write_leaves_nothing(tmp_path, monkeypatch, exc):
    monkeypatch.setattr(OpenEXR, "File", _failing_writer(exc))
    with pytest.raises(type(exc)):
        write_exr(tmp_path / "x.0001.exr", {"depth": np.zeros((H, W))})
    assert os.listdir(tmp_path) == []


def test_exr_failed_overwrite_keeps_previous_file(tmp_path, monkeypatch):
    path = write_exr(tmp_path / "x.exr", {"depth": np.full((H, W), 3.0)})
    before = path.read_bytes()
    monkeypatch.setattr(OpenEXR, "File", _failing_writer(KeyboardInterrupt()))
    with pytest.raises(KeyboardInterrupt):
        write_exr(path, {"depth": np.full((H, W), 4.0)})
    assert os.listdir(tmp_path) == ["x.exr"]
    assert path.read_bytes() == before and is_complete_exr(path)
    monkeypatch.undo()
    write_exr(path, {"depth": np.full((H, W), 4.0)})         # a good overwrite replaces it
    assert (read_exr(path)[0]["depth"] == 4.0).all()


def test_exr_write_creates_folders(tmp_path):
    path = write_exr(tmp_path / "a" / "b" / "x.exr", {"depth": np.zeros((H, W))})
    assert path.is_file() and os.listdir(path.parent) == ["x.exr"]


def test_is_complete_exr_truncated_and_junk(tmp_path):
    rng = np.random.default_rng(4)
    aovs = {"color": rng.random((64, 64, 4)), "P": rng.random((64, 64, 3))}
    path = write_exr(tmp_path / "full.exr", aovs)
    data = path.read_bytes()
    assert is_complete_exr(path)
    assert is_complete_exr(path, channels=["R", "P.X"])
    assert not is_complete_exr(path, channels=["R", "primId.id"])
    for cut in (10, 200, len(data) // 2, len(data) - 5):
        bad = tmp_path / f"cut{cut}.exr"
        bad.write_bytes(data[:cut])
        assert not is_complete_exr(bad), cut
    with pytest.raises(ExrError):
        read_exr(tmp_path / f"cut{len(data) // 2}.exr")
    (tmp_path / "junk.exr").write_bytes(b"not an exr at all")
    assert not is_complete_exr(tmp_path / "junk.exr")
    assert not is_complete_exr(tmp_path / "missing.exr")
    png = write_png_preview(tmp_path / "p.png", np.zeros((4, 4, 4)))
    assert not is_complete_exr(png)
    with pytest.raises(ExrError, match="no such"):
        read_exr(tmp_path / "missing.exr")


# --- PNG preview --------------------------------------------------------------------------------

def _read_png(path):
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)       # the stored (straight) values
    inp = oiio.ImageInput.open(str(path), config)
    spec = inp.spec()
    px = inp.read_image(oiio.UINT8)
    cs = spec.get_string_attribute("oiio:ColorSpace")
    inp.close()
    return spec, px, cs


def test_png_preview_is_8bit_srgb(tmp_path):
    rgba = np.zeros((2, 3, 4), np.float32)
    rgba[0, 0] = [0.5, 0.0, 1.0, 1.0]            # linear 0.5 -> sRGB 188
    rgba[0, 1] = [0.25, 0.25, 0.25, 0.5]         # premultiplied: straight 0.5 -> 188, alpha 128
    rgba[0, 2] = [4.0, np.nan, np.inf, 1.0]      # clamp; NaN -> 0; inf -> white
    rgba[1, 0] = [0.0031308, 0.001, 0.0, 1.0]    # linear segment of the sRGB curve
    path = write_png_preview(tmp_path / "prev.png", rgba)
    spec, px, cs = _read_png(path)
    assert spec.format == oiio.UINT8 and spec.nchannels == 4 and (spec.width, spec.height) == (3, 2)
    assert "srgb" in cs.lower() and b"sRGB" in path.read_bytes()[:200]      # PNG sRGB chunk
    assert list(px[0, 0]) == [188, 0, 255, 255]
    assert list(px[0, 1]) == [188, 188, 188, 128]
    assert list(px[0, 2]) == [255, 0, 255, 255]
    assert list(px[1, 0][:2]) == [10, 3]
    assert list(px[1, 1]) == [0, 0, 0, 0]
    assert os.listdir(tmp_path) == ["prev.png"]


def _srgb(x: float) -> float:
    """IEC 61966-2-1 encoding of a linear value in [0, 1]."""
    return 12.92 * x if x <= 0.0031308 else 1.055 * x ** (1 / 2.4) - 0.055


def test_png_preview_over_black_and_reinhard(tmp_path):
    rgba = np.zeros((1, 2, 4), np.float32)
    rgba[0, 0] = [0.25, 0.25, 0.25, 0.5]
    rgba[0, 1] = [3.0, 3.0, 3.0, 1.0]
    _, px, _ = _read_png(write_png_preview(tmp_path / "a.png", rgba, alpha=False, tonemap="reinhard"))
    assert px.shape == (1, 2, 3)
    assert px[0, 0, 0] == round(255 * _srgb(0.2))   # 0.25/(1+0.25)
    assert px[0, 1, 0] == round(255 * _srgb(0.75))  # 3/(1+3)
    _, px, _ = _read_png(write_png_preview(tmp_path / "b.png", rgba[..., :3], exposure=-1))
    assert px.shape == (1, 2, 3) and px[0, 0, 0] == round(255 * _srgb(0.125))
    with pytest.raises(ValueError):
        write_png_preview(tmp_path / "c.png", rgba, tonemap="filmic")
    with pytest.raises(ValueError):
        write_png_preview(tmp_path / "c.png", np.zeros((2, 2)))


# --- frame naming -------------------------------------------------------------------------------

@pytest.mark.parametrize("pattern, frame, expected", [
    ("out.####.exr", 12, "out.0012.exr"),
    ("out.####.exr", 12.0, "out.0012.exr"),
    ("out.#.exr", 1234, "out.1234.exr"),                 # never truncated
    ("out.####.##.exr", 12.5, "out.0012.50.exr"),       # width counts the dot: {:07.2f}
    ("out.###.#.exr", 1.25, "out.001.2.exr"),            # rounded (half-even, as Python formats)
    ("out.##.###.exr", 101.125, "out.101.125.exr"),
    ("out.####.exr", -3, "out.-003.exr"),                # the sign takes a place
    ("out.####.##.exr", -12.5, "out.-012.50.exr"),
    ("out.####.exr", -0.4, "out.0000.exr"),              # no "-000"
    ("/a/b_c/beauty_#####.exr", 7, "/a/b_c/beauty_00007.exr"),
])
def test_format_frame(pattern, frame, expected):
    assert format_frame(pattern, frame) == expected


@pytest.mark.parametrize("pattern, placeholder", [
    ("out.####.exr", "####"), ("out.##.#.exr", "##.#"), ("out.exr", None),
    ("a#/out.####.exr", None), ("out.#.#.#.exr", None), ("out.##_##.exr", None), ("", None),
])
def test_frame_placeholder(pattern, placeholder):
    assert frame_placeholder(pattern) == placeholder


def test_output_paths_usdrecord_rules():
    assert output_paths("b.####.exr", [1, 2, 3]) == ["b.0001.exr", "b.0002.exr", "b.0003.exr"]
    assert output_paths("b.####.exr", [7]) == ["b.0007.exr"]
    with pytest.raises(OutputPathError, match="no frame placeholder"):
        output_paths("b.exr", [1, 2])
    with pytest.raises(OutputPathError, match="no frame placeholder"):
        output_paths("b.exr", [1])                        # --frames given: placeholder required
    with pytest.raises(OutputPathError, match="outside one placeholder"):
        output_paths("shot#1/b.####.exr", [1, 2])
    assert output_paths("b.exr", [1001.0], frames_given=False) == ["b.exr"]
    with pytest.raises(OutputPathError, match="cannot contain a frame number placeholder"):
        output_paths("b.####.exr", [1001.0], frames_given=False)
    prec = frame_spec_precision("1:2x0.25")
    assert prec == 2
    with pytest.raises(OutputPathError, match="needs 2 decimal"):
        output_paths("b.####.#.exr", frame_spec("1:2x0.25"), min_precision=prec)
    assert output_paths("b.####.##.exr", frame_spec("1:1.5x0.25"), min_precision=prec) == [
        "b.0001.00.exr", "b.0001.25.exr", "b.0001.50.exr"]
    with pytest.raises(OutputPathError, match="both write"):
        output_paths("b.####.exr", frame_spec("1,1.25"))
    with pytest.raises(ValueError):                       # also a ValueError and a UsdmlError
        output_paths("b.exr", [1, 2])
    assert issubclass(OutputPathError, UsdmlError) and issubclass(FrameSpecError, UsdmlError)


# --- FrameSpec ----------------------------------------------------------------------------------

@pytest.mark.parametrize("spec, frames", [
    ("101:105", [101, 102, 103, 104, 105]),
    ("1:10x2", [1, 3, 5, 7, 9]),
    ("105:101", [105, 104, 103, 102, 101]),
    ("1:2x0.5", [1, 1.5, 2]),
    ("7", [7]),
    ("1,5,10:12", [1, 5, 10, 11, 12]),
    (" 1:2x0.5 , 7 ", [1, 1.5, 2, 7]),
    ("-3:-1", [-3, -2, -1]),
    ("10:1x-3", [10, 7, 4, 1]),
    ("12.5", [12.5]),
])
def test_frame_spec(spec, frames):
    assert frame_spec(spec, 1, 10) == [float(f) for f in frames]


def test_frame_spec_takes_timecodes_as_they_are():
    """The API's and a farm chunk's frames stay floats: no FrameSpec text (which held 6 digits) between."""
    assert frame_spec([1, 2.5, 12345.678], 1) == [1.0, 2.5, 12345.678]
    assert frame_spec_precision([1.25]) == 0 == frame_spec_precision("1,1.25")
    for bad in ([], [True], ["1"], [float("nan")]):
        with pytest.raises(FrameSpecError, match="give a FrameSpec"):
            frame_spec(bad, 1)


def test_frame_spec_default_is_stage_start():
    assert frame_spec(None, 1001.0, 1100.0) == [1001.0]
    assert frame_spec("  ", 3.0) == [3.0]
    with pytest.raises(FrameSpecError):
        frame_spec(None)


@pytest.mark.parametrize("spec, match", [
    ("1:10x0", "stride cannot be zero"), ("abc", "Invalid FrameSpec"), ("1:3:5", "1:3:5"),
    ("10:1x1", "endTimeCode cannot be less"), ("1,,2", "empty FrameSpec"), ("1x2", "1x2"),
    ("nan", "nan"), ("1:1e9", "more than"),
])
def test_frame_spec_errors(spec, match):
    with pytest.raises(FrameSpecError, match=match):
        frame_spec(spec, 1, 10)


def test_exr_says_its_colours_are_linear_rec709_d65(tmp_path):
    """Every EXR carries OpenEXR's ``chromaticities``: ITU-R BT.709's primaries and D65 white (the numbers from the
    recommendation, read back by OpenImageIO, a reader sharing no usdml code)."""
    from usdml.aov.exr import write_exr

    path = tmp_path / "c.exr"
    write_exr(path, {"color": np.zeros((2, 3, 4), np.float32)})
    spec = oiio.ImageInput.open(str(path)).spec()
    got = spec.getattribute("chromaticities")
    bt709 = (0.640, 0.330, 0.300, 0.600, 0.150, 0.060)
    d65 = (0.3127, 0.3290)
    np.testing.assert_allclose(got, bt709 + d65, atol=1e-6)
