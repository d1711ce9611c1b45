"""Tests of the synthetic volumes, volume IO and the float64 volume reference ray caster."""

import base64
import importlib.resources
import importlib.util
import lzma
import math
import sys
import zlib

import numpy as np
import pytest
from reference_volume64 import camera_rays, first_hits
from scipy.ndimage import map_coordinates

from jaxiso.io import load_volume, save_volume
from jaxiso.volume import data as vd

# ---- generators ---------------------------------------------------------------------------


def test_marschner_lobb_known_values():
    v = vd.marschner_lobb(41)
    assert v.shape == (41, 41, 41) and v.dtype == np.float32
    assert 0.0 <= v.min() and v.max() <= 1.0
    # x = y = 0: rho_r = cos(12 pi) = 1, so rho = (1 - sin(pi z / 2) + 2 alpha) / 2.5
    np.testing.assert_allclose(v[20, 20, [0, 20, 40]], [1.0, 0.6, 0.2], atol=1e-6)
    # x = y = 1, z = 0: r = sqrt 2, worked by hand with math
    rho_r = math.cos(12 * math.pi * math.cos(math.pi * math.sqrt(2) / 2))
    np.testing.assert_allclose(v[40, 40, 20], (1 + 0.25 * (1 + rho_r)) / 2.5, atol=1e-6)
    np.testing.assert_array_equal(v, v.transpose(1, 0, 2))  # radial in x, y
    np.testing.assert_allclose(vd.marschner_lobb(5, alpha=0.0)[2, 2, 2], 0.5, atol=1e-7)


def test_sphere_distance_values_and_shapes():
    v = vd.sphere_distance(9)
    assert v.dtype == np.float32
    np.testing.assert_allclose(v[0, 0, 0], math.sqrt(0.75) - 0.35, atol=1e-6)
    np.testing.assert_allclose(v[4, 4, 4], -0.35, atol=1e-7)
    w = vd.sphere_distance((5, 9, 17), radius=0.25, center=(0.5, 0.25, 0.0))
    assert w.shape == (5, 9, 17)
    np.testing.assert_allclose(w[2, 2, 0], -0.25, atol=1e-7)      # the centre node
    np.testing.assert_allclose(w[4, 2, 4], math.hypot(0.5, 0.25) - 0.25, atol=1e-6)


def test_box_geometry():
    spacing, origin = vd.box_geometry((5, 9, 17), -1.0, 1.0)
    assert spacing == (0.5, 0.25, 0.125) and origin == (-1.0, -1.0, -1.0)
    assert vd.box_geometry(3) == ((0.5,) * 3, (0.0,) * 3)
    with pytest.raises(ValueError):
        vd.box_geometry((4, 4))


def _layer_fraction(v):
    return np.mean((v != 0) & (v != 255))


def test_mixing_properties():
    a = vd.mixing(24, seed=3, time=1.0)
    assert a.shape == (24, 24, 24) and a.dtype == np.float32
    assert a.min() == 0.0 and a.max() == 255.0
    np.testing.assert_array_equal(a, vd.mixing(24, seed=3, time=1.0))   # deterministic
    assert np.all(a[:, :, 0] == 255) and np.all(a[:, :, -1] == 0)       # heavy below
    assert 0.5 < np.mean((a == 0) | (a == 255))                          # compressible
    assert not np.array_equal(a, vd.mixing(24, seed=4, time=1.0))
    assert not np.array_equal(a, vd.mixing(24, seed=3, time=1.1))
    fractions = [_layer_fraction(vd.mixing(24, seed=3, time=t)) for t in (0.0, 1.0, 3.0)]
    assert fractions[0] < fractions[1] < fractions[2]                    # the layer grows
    q = vd.mixing(24, seed=3, time=1.0, quantize=True)
    assert q.dtype == np.uint8
    np.testing.assert_array_equal(q, np.rint(a).astype(np.uint8))
    # both sides of the isovalue occur in the middle plane: the interface crosses it
    mid = a[:, :, 12]
    assert (mid > 127.5).any() and (mid < 127.5).any()
    with pytest.raises(ValueError):
        vd.mixing(8, time=-1.0)
    two = vd.mixing((3, 3, 2))                      # no node inside the layer
    assert np.all(two[:, :, 0] == 255) and np.all(two[:, :, 1] == 0)


def test_mixing_samples_one_continuous_field():
    fine, coarse = vd.mixing(33, time=2.0), vd.mixing(17, time=2.0)
    np.testing.assert_allclose(fine[::2, ::2, ::2], coarse, atol=1e-3)
    aniso = vd.mixing((17, 9, 33), time=2.0)
    np.testing.assert_allclose(aniso, fine[::2, ::4, :], atol=1e-3)


def test_ct_phantom():
    v = vd.ct_phantom(32)
    assert v.dtype == np.uint8 and v.shape == (32, 32, 32)
    assert set(np.unique(v)) <= {0, 30, 90, 140, 200}
    assert v[0, 0, 0] == 0 and v[16, 16, 16] == 90
    # x axis through y = 0, z = 0.05 (n = 201 -> x step 0.01): air, bone shell, tissue
    line = vd.ct_phantom((201, 3, 41))[:, 1, 21]
    assert line[100] == 90 and line[170] == 200 and line[175] == 0 and line[30] == 200
    # large uniform regions: most 2x2x2 blocks hold a single value
    blocks = v.reshape(16, 2, 16, 2, 16, 2).transpose(0, 2, 4, 1, 3, 5).reshape(-1, 8)
    assert np.mean(blocks.min(axis=1) == blocks.max(axis=1)) > 0.8


def test_examples_cover_domains_and_isovalues():
    ex = vd.examples()
    assert set(ex) == set(vd.DOMAINS) == set(vd.ISOVALUES)
    for name, make in ex.items():
        v = make(17)
        assert v.shape == (17, 17, 17), name
        assert v.min() < vd.ISOVALUES[name] < v.max(), name   # a non-empty isosurface


# ---- IO -----------------------------------------------------------------------------------


def test_npy_npz_round_trip(tmp_path):
    a = np.random.default_rng(0).random((3, 4, 5)).astype(np.float32)
    save_volume(tmp_path / "v.npy", a)
    b, meta = load_volume(tmp_path / "v.npy")
    np.testing.assert_array_equal(a, b)
    assert meta["format"] == "npy" and "spacing" not in meta
    with pytest.warns(UserWarning, match="spacing"):
        save_volume(tmp_path / "w.npy", a, spacing=(1, 2, 3))
    save_volume(tmp_path / "v.npz", a, spacing=(0.5, 1, 2), origin=(-1, 0, 1))
    b, meta = load_volume(tmp_path / "v.npz")
    np.testing.assert_array_equal(a, b)
    assert meta["spacing"] == (0.5, 1.0, 2.0) and meta["origin"] == (-1.0, 0.0, 1.0)
    np.savez(tmp_path / "one.npz", volume=a)
    np.testing.assert_array_equal(load_volume(tmp_path / "one.npz")[0], a)
    np.savez(tmp_path / "two.npz", x=a, y=a + 1)
    with pytest.raises(ValueError, match="two.npz.*'data'"):
        load_volume(tmp_path / "two.npz")
    np.testing.assert_array_equal(load_volume(tmp_path / "two.npz", array="y")[0], a + 1)
    with pytest.raises(ValueError, match=r"'z'.*\['x', 'y'\]"):
        load_volume(tmp_path / "two.npz", array="z")
    with pytest.raises(ValueError, match="array="):
        load_volume(tmp_path / "v.npy", array="x")
    with pytest.raises(ValueError, match="shape"):
        load_volume(tmp_path / "v.npy", shape=(5, 4, 3))


def test_raw_files(tmp_path):
    a = np.arange(60, dtype=np.int16).reshape(3, 4, 5)
    save_volume(tmp_path / "v.raw", a)
    b, meta = load_volume(tmp_path / "v.raw", shape=(3, 4, 5), dtype=np.int16)
    np.testing.assert_array_equal(a, b)
    assert meta["format"] == "raw"
    with pytest.raises(ValueError, match="v.raw.*shape= and dtype="):
        load_volume(tmp_path / "v.raw")
    with pytest.raises(ValueError, match="expected 240 bytes.*has 120 bytes"):
        load_volume(tmp_path / "v.raw", shape=(3, 4, 5), dtype=np.float32)
    # a 7-byte header, big-endian, first index fastest, an unknown extension
    (tmp_path / "v.dat").write_bytes(b"HEADER!" + a.astype(">u2").tobytes(order="F"))
    b, _ = load_volume(tmp_path / "v.dat", shape=(3, 4, 5), dtype=">u2", order="F", offset=7)
    np.testing.assert_array_equal(a, b)
    assert b.dtype == np.uint16 and b.dtype.byteorder in "=<"


def test_errors_name_the_file(tmp_path):
    (tmp_path / "bad.npy").write_bytes(b"not a numpy file at all")
    with pytest.raises(ValueError, match="bad.npy"):
        load_volume(tmp_path / "bad.npy")
    with pytest.raises(FileNotFoundError, match="missing.npy"):
        load_volume(tmp_path / "missing.npy")
    with pytest.raises(ValueError, match="cannot write"):
        save_volume(tmp_path / "v.png", np.zeros((2, 2, 2)))


def test_nifti_round_trip(tmp_path):
    nib = pytest.importorskip("nibabel")
    a = np.random.default_rng(1).random((4, 3, 2)).astype(np.float32)
    path = save_volume(tmp_path / "v.nii.gz", a, spacing=(0.5, 1.5, 2.0), origin=(1, 2, 3))
    expected = np.array([[0.5, 0, 0, 1], [0, 1.5, 0, 2], [0, 0, 2, 3], [0, 0, 0, 1]])
    np.testing.assert_allclose(nib.load(str(path)).affine, expected)
    b, meta = load_volume(path)
    np.testing.assert_array_equal(a, b)
    assert meta["spacing"] == (0.5, 1.5, 2.0) and meta["origin"] == (1.0, 2.0, 3.0)
    assert meta["format"] == "nifti" and meta["axis_aligned"] and "time_axis" not in meta


def test_nifti_4d_example():
    pytest.importorskip("nibabel")
    path = importlib.resources.files("nibabel") / "tests" / "data" / "example4d.nii.gz"
    if not path.is_file():
        pytest.skip("nibabel ships no example4d.nii.gz here")
    data, meta = load_volume(str(path))
    assert data.shape == (128, 96, 24, 2) and meta["time_axis"] == 3
    np.testing.assert_allclose(meta["spacing"], (2.0, 2.0, 2.2), rtol=1e-6)
    np.testing.assert_allclose(meta["origin"], (117.855103, -35.7229424, -7.24879837),
                               rtol=1e-6)
    assert meta["time_step"] == 2000.0 and not meta["axis_aligned"]   # a tilted slab


def test_nifti_errors(tmp_path, monkeypatch):
    pytest.importorskip("nibabel")
    (tmp_path / "bad.nii.gz").write_bytes(b"\x1f\x8b garbage")
    with pytest.raises(ValueError, match="bad.nii.gz"):
        load_volume(tmp_path / "bad.nii.gz")
    monkeypatch.setitem(sys.modules, "nibabel", None)   # import nibabel now fails
    with pytest.raises(ImportError, match=r"jaxiso\[data\]"):
        load_volume(tmp_path / "bad.nii.gz")


def _b64(raw: bytes) -> str:
    return base64.b64encode(raw).decode()


def _encode_array(values, mode, header):
    """DataArray (attributes, inline text, appended bytes) for one array, x fastest."""
    raw = np.ascontiguousarray(values.ravel(order="F")).tobytes()
    h = np.dtype({"UInt32": "<u4", "UInt64": "<u8"}[header])
    if mode == "ascii":
        return 'format="ascii"', " ".join(map(repr, values.ravel(order="F").tolist())), b""
    if mode == "binary-joint":
        return 'format="binary"', _b64(np.array([len(raw)], h).tobytes() + raw), b""
    if mode == "binary-split":
        return 'format="binary"', _b64(np.array([len(raw)], h).tobytes()) + _b64(raw), b""
    blocks = [raw[i:i + 64] for i in range(0, len(raw), 64)]       # several blocks
    packed = [(lzma.compress if "lzma" in mode else zlib.compress)(b) for b in blocks]
    table = np.array([len(blocks), 64, len(blocks[-1]) % 64] + [len(p) for p in packed], h)
    if mode == "binary-zlib":
        return 'format="binary"', _b64(table.tobytes()) + _b64(b"".join(packed)), b""
    if mode in ("appended-zlib", "appended-lzma"):
        return 'format="appended"', "", table.tobytes() + b"".join(packed)
    if mode == "appended-b64":
        return 'format="appended"', "", (_b64(np.array([len(raw)], h).tobytes())
                                         + _b64(raw)).encode()
    raise AssertionError(mode)


def _write_vti(path, arrays, *, mode, header="UInt32", spacing=(1, 1, 1), origin=(0, 0, 0),
               start=(0, 0, 0), scalars=None):
    shape = next(iter(arrays.values())).shape
    ext = " ".join(f"{s} {s + n - 1}" for s, n in zip(start, shape))
    compressor = {"zlib": "vtkZLibDataCompressor", "lzma": "vtkLZMADataCompressor"}.get(
        mode.rsplit("-", 1)[-1])
    parts, payload = [], b""
    for name, values in arrays.items():
        attrs, text, blob = _encode_array(values, mode, header)
        vtk_type = {"f4": "Float32", "f8": "Float64", "u1": "UInt8",
                    "i2": "Int16"}[values.dtype.str[1:]]
        offset = f' offset="{len(payload)}"' if blob else ""
        parts.append(f'<DataArray type="{vtk_type}" Name="{name}" {attrs}{offset}>{text}'
                     "</DataArray>")
        payload += blob
    head = (f'<?xml version="1.0"?>\n<VTKFile type="ImageData" version="1.0" '
            f'byte_order="LittleEndian" header_type="{header}"'
            + (f' compressor="{compressor}"' if compressor else "") + ">\n"
            f'<ImageData WholeExtent="{ext}" Origin="{" ".join(map(str, origin))}" '
            f'Spacing="{" ".join(map(str, spacing))}">\n<Piece Extent="{ext}">\n'
            + (f'<PointData Scalars="{scalars}">' if scalars else "<PointData>")
            + "".join(parts) + "</PointData>\n</Piece>\n</ImageData>\n")
    tail = b"</VTKFile>\n"
    if payload:
        encoding = "base64" if mode == "appended-b64" else "raw"
        appended = f'<AppendedData encoding="{encoding}">\n_'.encode() + payload
        appended += b"\n</AppendedData>\n"
        path.write_bytes(head.encode() + appended + tail)
    else:
        path.write_bytes(head.encode() + tail)


@pytest.mark.parametrize("mode", ["ascii", "binary-joint", "binary-split", "binary-zlib",
                                  "appended-zlib", "appended-lzma", "appended-b64"])
@pytest.mark.parametrize("header", ["UInt32", "UInt64"])
def test_vti_encodings(tmp_path, mode, header):
    rng = np.random.default_rng(2)
    a = rng.random((5, 4, 3))                       # float64: 480 bytes, 8 zlib blocks
    b = rng.integers(0, 255, (5, 4, 3)).astype(np.uint8)
    path = tmp_path / "v.vti"
    _write_vti(path, {"density": a, "label": b}, mode=mode, header=header,
               spacing=(0.5, 1, 2), origin=(1, 2, 3), start=(2, 0, 1))
    got, meta = load_volume(path)                  # the first array by default
    np.testing.assert_array_equal(got, a)
    assert meta["spacing"] == (0.5, 1.0, 2.0)
    assert meta["origin"] == (2.0, 2.0, 5.0)       # Origin + extent start * Spacing
    got, meta = load_volume(path, array="label")
    np.testing.assert_array_equal(got, b)
    assert got.dtype == np.uint8 and meta["array"] == "label"


def test_vti_scalars_and_errors(tmp_path):
    a = np.arange(24, dtype=np.float32).reshape(2, 3, 4)
    path = tmp_path / "v.vti"
    _write_vti(path, {"a": a, "b": a + 1}, mode="ascii", scalars="b")
    np.testing.assert_array_equal(load_volume(path)[0], a + 1)
    with pytest.raises(ValueError, match=r"v.vti.*'c'.*\['a', 'b'\]"):
        load_volume(path, array="c")
    path.write_bytes(path.read_bytes()[:200])      # truncated
    with pytest.raises(ValueError, match="v.vti"):
        load_volume(path)
    _write_vti(path, {"a": a}, mode="ascii")
    path.write_text(path.read_text().replace("vtkZLib", "").replace(
        'header_type="UInt32"', 'header_type="UInt32" compressor="vtkLZ4DataCompressor"'))
    if importlib.util.find_spec("pyvista") is None:
        with pytest.raises(ValueError, match="v.vti.*vtkLZ4DataCompressor.*pyvista"):
            load_volume(path)


def test_vti_written_by_pyvista(tmp_path):
    pv = pytest.importorskip("pyvista", reason="pyvista is not installed (optional)")
    a = np.random.default_rng(5).random((4, 3, 2))
    grid = pv.ImageData(dimensions=a.shape, spacing=(0.5, 1.0, 2.0), origin=(1.0, 2.0, 3.0))
    grid.point_data["v"] = a.ravel(order="F")      # VTK runs x fastest
    grid.save(str(tmp_path / "p.vti"))
    got, meta = load_volume(tmp_path / "p.vti")
    np.testing.assert_array_equal(got, a)
    assert meta["spacing"] == (0.5, 1.0, 2.0) and meta["origin"] == (1.0, 2.0, 3.0)


# ---- the float64 reference ray caster -----------------------------------------------------


def _world_clip(lo, hi, o, d):
    """Slab clipping in world coordinates, written independently of the reference."""
    t0, t1 = np.zeros(len(o)), np.full(len(o), np.inf)
    for a in range(3):
        with np.errstate(divide="ignore"):
            ta, tb = (lo[a] - o[:, a]) / d[:, a], (hi[a] - o[:, a]) / d[:, a]
        t0, t1 = np.maximum(t0, np.minimum(ta, tb)), np.minimum(t1, np.maximum(ta, tb))
    return t0, t1


def _interp(data, points, spacing, origin):
    """F at world points [P, 3] by scipy's linear spline (= trilinear interpolation)."""
    idx = (points - np.asarray(origin)) / np.asarray(spacing)
    return map_coordinates(np.asarray(data, np.float64), idx.T, order=1, mode="nearest")


def _random_rays(rng, n, lo, hi):
    """Rays from points around the box towards points inside it."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    size = hi - lo
    o = lo - 0.6 * size + 2.2 * size * rng.random((n, 3))
    target = lo + size * rng.random((n, 3))
    return o, target - o


def test_camera_rays_match_jaxiso_camera():
    from jaxiso.render import Camera
    cam = Camera.look_at((2.0, -3.0, 1.5), (0.1, 0.2, 0.3), (0.0, 0.0, 1.0), 35.0, 7, 5)
    rays = cam.rays()
    o, d = camera_rays((2.0, -3.0, 1.5), (0.1, 0.2, 0.3), (0.0, 0.0, 1.0), 35.0, 7, 5)
    np.testing.assert_allclose(d, np.asarray(rays.direction).reshape(-1, 3), atol=2e-6)
    np.testing.assert_allclose(o, np.asarray(rays.origin).reshape(-1, 3), atol=1e-6)
    forward = -np.array([1.9, -3.2, 1.2]) / np.linalg.norm([1.9, -3.2, 1.2])
    np.testing.assert_allclose(d[2 * 7 + 3], forward, atol=1e-15)   # the centre pixel
    assert d[0, 2] > d[-1, 2]                                        # row 0 at the top


def test_linear_field_roots_are_exact():
    spacing, origin = (0.5, 2.0, 0.25), (-3.0, 1.0, 2.0)
    shape = (7, 4, 9)
    z = origin[2] + spacing[2] * np.arange(shape[2])
    data = np.broadcast_to(z, shape)                 # F = z exactly (trilinear of linear)
    lo, hi = np.array(origin), np.array(origin) + spacing * (np.array(shape) - 1)
    rng = np.random.default_rng(3)
    o, d = _random_rays(rng, 400, lo, hi)
    iso = 3.1
    t, hit, which = first_hits(data, o, d, iso, spacing=spacing, origin=origin)
    t_true = (iso - o[:, 2]) / d[:, 2]
    t0, t1 = _world_clip(lo, hi, o, d)
    inside = (t_true >= t0) & (t_true <= t1)
    clear = (np.minimum(t_true - t0, t1 - t_true) * np.linalg.norm(d, axis=1)) > 1e-9
    assert 50 < inside.sum() < 350
    np.testing.assert_array_equal(hit[clear], inside[clear])
    np.testing.assert_allclose(t[hit], t_true[hit], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(which, np.where(hit, 0, -1))
    assert np.all(np.isinf(t[~hit]))


def _sphere_case(n=16):
    data = vd.sphere_distance(n)
    spacing, origin = vd.box_geometry(data.shape)
    return data, spacing, origin


def test_sphere_hits_lie_on_the_interpolant_and_near_the_sphere():
    data, spacing, origin = _sphere_case()
    o, d = camera_rays((1.6, 1.1, 0.9), (0.5, 0.5, 0.5), (0, 0, 1), 40.0, 24, 24)
    t, hit, which = first_hits(data, o, d, 0.0, spacing=spacing, origin=origin)
    p = o + t[:, None] * d
    np.testing.assert_allclose(_interp(data, p[hit], spacing, origin), 0.0, atol=1e-9)
    voxel = spacing[0]
    assert np.all(np.abs(np.linalg.norm(p[hit] - 0.5, axis=1) - 0.35) < voxel)
    # rays clearly inside / outside the sphere's silhouette must hit / miss
    foot = o + np.einsum("ij,ij->i", 0.5 - o, d)[:, None] * d
    dist = np.linalg.norm(foot - 0.5, axis=1)
    assert hit[dist < 0.35 - voxel].all() and not hit[dist > 0.35 + voxel].any()
    assert 0.2 < hit.mean() < 0.8
    np.testing.assert_array_equal(which, np.where(hit, 0, -1))


def test_no_earlier_root_by_dense_sampling():
    rng = np.random.default_rng(4)
    data = rng.standard_normal((5, 6, 5))
    spacing, origin = (0.3, 0.2, 0.25), (0.1, -0.2, 0.0)
    lo = np.array(origin)
    hi = lo + np.array(spacing) * (np.array(data.shape) - 1)
    o, d = _random_rays(rng, 60, lo, hi)
    iso = (0.4, -0.7)
    t, hit, which = first_hits(data, o, d, iso, spacing=spacing, origin=origin)
    assert 10 < hit.sum() < 60
    t0, t1 = _world_clip(lo, hi, o, d)
    for r in range(len(o)):
        if t0[r] >= t1[r]:
            assert not hit[r]
            continue
        end = t[r] - 1e-9 if hit[r] else t1[r]
        s = np.linspace(t0[r], end, 20001)
        f = _interp(data, o[r] + s[:, None] * d[r], spacing, origin)
        for v in iso:          # no sign change of F - iso before the reported hit
            assert np.all(np.sign(f - v) == np.sign(f[0] - v)), (r, v)
        if hit[r]:
            f_hit = _interp(data, (o[r] + t[r] * d[r])[None], spacing, origin)[0]
            assert abs(f_hit - iso[which[r]]) < 1e-9


def test_rays_missing_the_box():
    data, spacing, origin = _sphere_case(8)
    o = np.array([[2.0, 0.5, 0.5], [0.5, 0.5, 3.0], [-1.0, 2.0, 0.5], [0.5, 0.5, 0.5]])
    d = np.array([[1.0, 0.0, 0.0], [0.0, 0.3, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    t, hit, which = first_hits(data, o, d, 0.0, spacing=spacing, origin=origin)
    assert not hit.any() and np.all(np.isinf(t)) and np.all(which == -1)
    # an array without cells along one axis has no surface
    assert not first_hits(data[:1], o, d, 0.0, spacing=spacing, origin=origin)[1].any()


def test_camera_inside_the_volume():
    data, spacing, origin = _sphere_case()
    o, d = camera_rays((0.5, 0.5, 0.5), (1.0, 0.8, 0.6), (0, 0, 1), 60.0, 8, 8)
    t, hit, _ = first_hits(data, o, d, 0.0, spacing=spacing, origin=origin)
    assert hit.all()                                  # inside the sphere: every ray exits
    np.testing.assert_allclose(t, 0.35, atol=spacing[0])
    o, d = camera_rays((0.15, 0.15, 0.2), (0.5, 0.5, 0.5), (0, 0, 1), 10.0, 4, 4)
    t, hit, _ = first_hits(data, o, d, 0.0, spacing=spacing, origin=origin)
    dist = np.linalg.norm([0.35, 0.35, 0.3])
    assert hit.all()
    np.testing.assert_allclose(t, dist - 0.35, atol=2 * spacing[0])


def _ramp_x(n=11):
    """F = x on [0, 1]^3 sampled at n nodes per axis."""
    return np.broadcast_to(np.linspace(0.0, 1.0, n)[:, None, None], (n, n, n)).copy()


def test_several_isovalues_order_and_t_range():
    data = _ramp_x()
    sp, org = (0.1,) * 3, (0.0,) * 3
    o = np.array([[-1.0, 0.45, 0.52], [2.0, 0.45, 0.52]])
    d = np.array([[1.0, 0.0, 0.0], [-2.0, 0.0, 0.0]])
    t, hit, which = first_hits(data, o, d, (0.73, 0.31), spacing=sp, origin=org)
    np.testing.assert_allclose(t, [1.31, (2.0 - 0.73) / 2], atol=1e-12)
    np.testing.assert_array_equal(which, [1, 0])
    t, hit, which = first_hits(data, o[:1], d[:1], (0.73, 0.31), spacing=sp, origin=org,
                               t_min=1.5)
    np.testing.assert_allclose(t, [1.73], atol=1e-12)
    assert which[0] == 0
    t, hit, _ = first_hits(data, o[:1], d[:1], 0.31, spacing=sp, origin=org, t_max=1.3)
    assert not hit[0]
    # a root on the box face: the entry point itself
    t, hit, _ = first_hits(data, o[:1], d[:1], 0.0, spacing=sp, origin=org)
    np.testing.assert_allclose(t, [1.0], atol=1e-12)


def test_non_finite_voxels_empty_their_cells():
    data = _ramp_x()
    data[3, 4:7, 4:7] = np.nan          # voxels at x = 0.3 around the ray
    data[6, 5, 5] = -np.inf             # and one at x = 0.6
    sp, org = (0.1,) * 3, (0.0,) * 3
    o = np.array([[-1.0, 0.45, 0.52], [-1.0, 0.05, 0.05]])
    d = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    # the ray at y = 0.45, z = 0.52 runs through cells x in [0.2, 0.4] and [0.5, 0.7]
    t, hit, which = first_hits(data, o, d, (0.25, 0.65, 0.85), spacing=sp, origin=org)
    np.testing.assert_allclose(t, [1.85, 1.25], atol=1e-12)
    np.testing.assert_array_equal(which, [2, 0])
    t, hit, _ = first_hits(data, o[:1], d[:1], 0.35, spacing=sp, origin=org)
    assert not hit[0]
