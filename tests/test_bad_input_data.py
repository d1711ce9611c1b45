"""Bad inputs to the data layer (tet meshes, volumes, .vti files, the command line): each
ends in a clear error naming the offending value. Sections follow the probes that found
them: 1 all-degenerate meshes, 2 `TetMesh` built directly, 3 volume geometry and dtype,
4 inconsistent .vti files, 5 command-line arguments."""

import base64
import os
import re

import numpy as np
import pytest

import jaxiso
from jaxiso import cli
from jaxiso.io import load_volume
from jaxiso.tetra import TetIsosurface, TetMesh, build_bvh, tet_mesh
from jaxiso.tetra import data as td
from jaxiso.volume import MacrocellGrid, OctreeVolume
from jaxiso.volume import data as vd

# A unit tet plus one more above it, and a flat quad split into one zero-volume tet.
POINTS = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], np.float64)
TETS = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
FLAT = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float64)
VOXELS = np.random.default_rng(0).random((6, 5, 4)).astype(np.float32)


# ---- 1. an all-degenerate tet mesh --------------------------------------------------------


def test_all_degenerate_tet_mesh_is_refused_by_tet_mesh():
    with pytest.raises(ValueError, match=r"all 2 tets are degenerate .*nothing to render"):
        tet_mesh(FLAT, [[0, 1, 2, 3], [0, 1, 3, 3]], np.zeros(4))


def test_all_degenerate_tet_mesh_is_refused_by_build_bvh_and_the_scene():
    raw = TetMesh(FLAT, np.array([[0, 1, 2, 3]]), np.zeros(4))  # the constructor allows it
    with pytest.raises(ValueError, match=r"all 1 tets are degenerate .*nothing to render"):
        build_bvh(raw)
    with pytest.raises(ValueError, match="all 1 tets are degenerate"):
        TetIsosurface(raw, 0.5)
    # vertices moved onto one plane: with_points warns, the next build refuses
    good = tet_mesh(POINTS, TETS, np.arange(5.0))
    squashed = POINTS * [1, 1, 0]
    with pytest.warns(UserWarning, match="degenerate"):
        flat = good.with_points(squashed)
    with pytest.raises(ValueError, match="all 2 tets are degenerate"):
        build_bvh(flat)


def test_some_degenerate_tets_still_build():
    points = np.concatenate([POINTS, FLAT + [5, 0, 0]])
    tets = np.concatenate([TETS, [[5, 6, 7, 8]]])
    with pytest.warns(UserWarning, match="1 degenerate tets"):
        mesh = tet_mesh(points, tets, np.arange(9.0))
    bvh = build_bvh(mesh, leaf_size=1)
    np.testing.assert_array_equal(np.sort(bvh.order), [0, 1])


# ---- 2. TetMesh(points, tets, values) constructed directly --------------------------------


def test_tetmesh_constructor_accepts_values_of_one_step():
    mesh = TetMesh(POINTS, TETS, np.arange(5.0))
    assert mesh.values.shape == (1, 5) and mesh.values.dtype == np.float32
    assert mesh.points.dtype == np.float32 and mesh.tets.dtype == np.int32
    assert build_bvh(mesh).order.size == 2
    assert TetMesh(POINTS.tolist(), TETS.tolist(), [0, 1, 2, 3, 4]).n_steps == 1


@pytest.mark.parametrize("change, error, words", [
    (dict(values=np.zeros(4)), ValueError, r"values must be \[V\] or \[S, V\] with V = 5, "
                                           r"got shape \(4,\)"),
    (dict(values=np.zeros((2, 5, 1))), ValueError, r"got shape \(2, 5, 1\)"),
    (dict(points=POINTS[:, :2]), ValueError, r"points must be \[V, 3\].*\(5, 2\)"),
    (dict(tets=TETS[:, :3]), ValueError, r"tets must be \[T, 4\], got shape \(2, 3\)"),
    (dict(tets=TETS.astype(float)), TypeError, "integer vertex indices, got dtype float64"),
    (dict(tets=[[0, 1, 2, 5]]), IndexError, r"tet 0 has vertex indices \[0, 1, 2, 5\] "
                                            r"outside \[0, 5\)"),
    (dict(tets=[[0, 1, 2, 3], [-1, 1, 2, 3]]), IndexError, r"tet 1 .*\[-1, 1, 2, 3\]"),
    (dict(points=np.where(np.arange(5)[:, None] == 3, np.nan, POINTS)), ValueError,
     r"1 points have non-finite coordinates \(first: point 3\)"),
    (dict(values=[0, 1, np.inf, 3, 4]), ValueError, r"non-finite \(first: step 0, vertex 2\)"),
    (dict(values=np.arange(5) + 1j), TypeError, "values must hold real numbers.*complex"),
    (dict(points=POINTS + 0j), TypeError, "points must hold real numbers.*complex"),
])
def test_tetmesh_constructor_checks_host_arrays(change, error, words):
    args = dict(points=POINTS, tets=TETS, values=np.arange(5.0)) | change
    with pytest.raises(error, match=words):
        TetMesh(**args)


def test_tetmesh_constructor_leaves_jax_arrays_and_tracers_alone():
    import dataclasses

    import jax
    import jax.numpy as jnp

    mesh = TetMesh(POINTS, TETS, np.arange(5.0))
    # pytree rebuilds (leaves replaced by placeholders) and jit must still work
    assert jax.tree.map(lambda a: None, mesh).points is None
    out = jax.jit(lambda m: m.values.sum())(mesh)
    assert float(out) == 10.0
    batched = dataclasses.replace(mesh, values=jnp.zeros((3, 1, 5)))  # e.g. a vmap batch
    assert batched.values.shape == (3, 1, 5)


# ---- 3. volumes: spacing, origin, dtype, macrocell levels ---------------------------------


@pytest.mark.parametrize("build", [MacrocellGrid.from_array, OctreeVolume.from_array],
                         ids=["grid", "octree"])
@pytest.mark.parametrize("spacing, error, words", [
    (0, ValueError, r"spacing must be > 0 on every axis, got 0"),
    (-1, ValueError, r"spacing must be > 0 on every axis, got -1"),
    (float("nan"), ValueError, r"spacing must be finite, got nan"),
    ((1, 0, 1), ValueError, r"spacing must be > 0 on every axis, got \(1, 0, 1\)"),
    (1e-60, ValueError, r"spacing must be > 0 .*1e-60"),   # 0 in float32
    ((1, 2), ValueError, r"spacing must be a scalar or a 3-vector, got shape \(2,\)"),
    (1j, TypeError, r"spacing must be a real scalar or 3-vector, got 1j"),
])
def test_volume_from_array_bad_spacing(build, spacing, error, words):
    with pytest.raises(error, match=words):
        build(VOXELS, spacing=spacing)


@pytest.mark.parametrize("build", [MacrocellGrid.from_array, OctreeVolume.from_array],
                         ids=["grid", "octree"])
def test_volume_from_array_bad_origin(build):
    with pytest.raises(ValueError, match=r"origin must be finite, got \(0, inf, 0\)"):
        build(VOXELS, origin=(0, float("inf"), 0))


@pytest.mark.parametrize("build, who", [(MacrocellGrid.from_array, "macrocell grids"),
                                        (OctreeVolume.from_array, "octree volumes")],
                         ids=["grid", "octree"])
def test_volume_from_array_complex_data(build, who):
    with pytest.raises(TypeError, match=f"{who} hold real numbers; got dtype complex64"):
        build(VOXELS + 1j * VOXELS)
    with pytest.raises(TypeError, match=f"{who} hold real numbers; got dtype object"):
        build(np.full((2, 2, 2), None))


@pytest.mark.parametrize("levels, words", [
    ((0, -1), r"levels must be ints in \[1, 20\].*got \(0, -1\) \(bad: \[0, -1\]\)"),
    ((3, 1.5), r"bad: \[1.5\]"),
    ((40,), r"bad: \[40\]"),                     # 2^40-wide macrocells
    ((float("nan"),), r"bad: \[nan\]"),
])
def test_macrocell_grid_bad_levels(levels, words):
    with pytest.raises(ValueError, match=words):
        MacrocellGrid.from_array(VOXELS, levels=levels)
    with pytest.raises(TypeError, match="levels must be an int or a sequence of ints"):
        MacrocellGrid.from_array(VOXELS, levels=("a",))


def test_macrocell_grid_wide_levels_stay_small():
    """A macrocell wider than the volume is one block, without padding to its width."""
    grid = MacrocellGrid.from_array(VOXELS, levels=20)
    assert grid.levels == (20,)
    (lo, hi), = grid.ranges
    assert lo.shape == (1, 1, 1) and float(lo[0, 0, 0]) == VOXELS.min()
    assert float(hi[0, 0, 0]) == VOXELS.max()
    fine = MacrocellGrid.from_array(VOXELS, levels=(1,))
    assert fine.ranges[0][0].shape == (3, 2, 2)   # 5 x 4 x 3 cells in 2-wide blocks


@pytest.mark.parametrize("call, words", [
    (lambda: vd.marschner_lobb(2.5), r"positive sizes, got 2.5"),
    (lambda: vd.sphere_distance(float("nan")), r"positive sizes, got nan"),
    (lambda: vd.ct_phantom((4, 4)), r"positive sizes, got \(4, 4\)"),
    (lambda: vd.mixing(4, time=float("nan")), r"time must be >= 0, got nan"),
    (lambda: vd.box_geometry(4, 1.0, 0.0), r"finite lo < hi, got lo=1.0, hi=0.0"),
    (lambda: td.cube_tets(2.5), r"n must be a positive int or 3 of them, got 2.5"),
    (lambda: td.replicate(*td.cube_tets(1), np.zeros(8), float("nan")),
     r"k must be a positive int, got nan"),
    (lambda: td.time_series(POINTS, 0), r"steps must be a positive int, got 0"),
])
def test_synthetic_data_bad_sizes(call, words):
    with pytest.raises(ValueError, match=words):
        call()


# ---- 4. inconsistent .vti files -----------------------------------------------------------


def _vti(path, whole, pieces, *, binary_values=None):
    """A hand-written ascii .vti: pieces [(extent, values text)]; `binary_values` replaces
    the first piece's data by a base64 binary array of those float32 values."""
    body = []
    for i, (extent, text) in enumerate(pieces):
        fmt = 'format="ascii"'
        if i == 0 and binary_values is not None:
            raw = np.asarray(binary_values, "<f4").tobytes()
            text = base64.b64encode(np.array([len(raw)], "<u4").tobytes() + raw).decode()
            fmt = 'format="binary"'
        body.append(f'<Piece Extent="{extent}"><PointData><DataArray type="Float32" '
                    f'Name="a" {fmt}>{text}</DataArray></PointData></Piece>')
    path.write_text('<?xml version="1.0"?>\n<VTKFile type="ImageData" version="1.0" '
                    'byte_order="LittleEndian" header_type="UInt32">'
                    f'<ImageData WholeExtent="{whole}" Origin="0 0 0" Spacing="1 1 1">'
                    + "".join(body) + "</ImageData></VTKFile>\n")
    return path


def test_vti_two_pieces_sharing_a_face_load(tmp_path):
    path = _vti(tmp_path / "v.vti", "0 2 0 0 0 0", [("0 1 0 0 0 0", "1 2"),
                                                    ("1 2 0 0 0 0", "2 3")])
    np.testing.assert_array_equal(load_volume(path)[0].ravel(), [1, 2, 3])


def test_vti_pieces_cover_part_of_whole_extent(tmp_path):
    path = _vti(tmp_path / "part.vti", "0 3 0 1 0 0", [("0 1 0 1 0 0", "1 2 3 4")])
    with pytest.raises(ValueError, match=r"part.vti.*do not cover WholeExtent '0 3 0 1 0 0'"
                                         r": nothing holds extent '2 3 0 1 0 0'"):
        load_volume(path)


def test_vti_piece_with_too_many_values(tmp_path):
    path = _vti(tmp_path / "many.vti", "0 1 0 1 0 0", [("0 1 0 1 0 0", "1 2 3 4 5")])
    with pytest.raises(ValueError, match=r"many.vti.*Piece 0: array 'a' holds 5 values, "
                                         r"its Extent needs 4"):
        load_volume(path)
    _vti(path, "0 1 0 1 0 0", [("0 1 0 1 0 0", "")], binary_values=np.arange(6))
    with pytest.raises(ValueError, match="holds 6 values, its Extent needs 4"):
        load_volume(path)


def test_vti_huge_extent_in_a_tiny_file(tmp_path):
    whole = "0 99999 0 99999 0 99999"  # 10^15 voxels: a bare MemoryError if allocated
    path = _vti(tmp_path / "huge.vti", whole, [("0 1 0 1 0 0", "1 2 3 4")])
    assert os.path.getsize(path) < 400
    with pytest.raises(ValueError, match=rf"huge.vti.*do not cover WholeExtent '{whole}'"):
        load_volume(path)
    _vti(path, whole, [(whole, "1 2 3 4")])  # the piece claims it all
    with pytest.raises(ValueError, match=r"holds 4 values, its Extent needs "
                                         r"1000000000000000"):
        load_volume(path)


@pytest.mark.parametrize("whole, piece, words", [
    ("0 1 0 1 0 0", "0 2 0 1 0 0", r"Piece 0 Extent '0 2 0 1 0 0' lies outside "
                                   r"WholeExtent '0 1 0 1 0 0'"),
    ("0 1 1 0 0 0", "0 1 0 1 0 0", r"WholeExtent must be six ints .*got '0 1 1 0 0 0'"),
    ("0 1 0 1 0", "0 1 0 1 0 0", r"WholeExtent must be six ints .*got '0 1 0 1 0'"),
    ("0 1 0 1 0 0", "1 0 0 1 0 0", r"Piece 0 Extent must be six ints"),
])
def test_vti_malformed_extents(tmp_path, whole, piece, words):
    path = _vti(tmp_path / "ext.vti", whole, [(piece, "1 2 3 4")])
    with pytest.raises(ValueError, match="ext.vti.*" + words):
        load_volume(path)


# ---- 5. the command line ------------------------------------------------------------------


@pytest.fixture
def no_work(monkeypatch):
    """Fail the test if the command gets as far as rendering or computing anything."""
    def refuse(args):
        raise AssertionError("bad arguments reached the work")
    monkeypatch.setattr(cli, "_gallery", refuse)
    monkeypatch.setattr(cli, "_demo", refuse)


def _usage_error(capsys, argv, pattern):
    with pytest.raises(SystemExit) as exit_info:
        cli.main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    last = err.strip().splitlines()[-1]
    assert re.search(pattern, last), err
    return last


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="needs a /proc file system")
def test_cli_gallery_out_proc(capsys, no_work):
    _usage_error(capsys, ["gallery", "--out", "/proc/x"],
                 r"^jaxiso gallery: error: --out /proc/x: cannot create the directory")


@pytest.mark.skipif(not os.path.exists("/dev/null"), reason="needs /dev/null")
def test_cli_gallery_out_dev_null(capsys, no_work):
    _usage_error(capsys, ["gallery", "--out", "/dev/null"],
                 r"^jaxiso gallery: error: --out /dev/null: not a directory$")


def test_cli_gallery_out_under_a_file(capsys, no_work, tmp_path):
    file = tmp_path / "f.txt"
    file.write_text("x")
    _usage_error(capsys, ["gallery", "--out", str(file)], r"f.txt: not a directory$")
    _usage_error(capsys, ["gallery", "--out", str(file / "sub")],
                 r"f.txt/sub: cannot create the directory")


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0,
                    reason="root may write to any directory")
def test_cli_gallery_out_not_writable(capsys, no_work, tmp_path):
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    try:
        _usage_error(capsys, ["gallery", "--out", str(locked)], r"is not writable$")
    finally:
        locked.chmod(0o700)


def test_cli_demo_names_bad(capsys, no_work):
    last = _usage_error(capsys, ["demo", "--names", "sphere", "bad"],
                        r"^jaxiso demo: error: unknown surfaces: bad; known: sphere, ")
    assert all(n in last for n in jaxiso.surfaces.names())


def test_cli_gallery_names_bad(capsys, no_work, tmp_path):
    _usage_error(capsys, ["gallery", "--out", str(tmp_path), "--names", "nope", "bad"],
                 r"^jaxiso gallery: error: unknown surfaces: nope, bad; known: ")


def test_cli_demo_seed_negative(capsys, no_work):
    _usage_error(capsys, ["demo", "--seed", "-1"],
                 r"^jaxiso demo: error: --seed must be >= 0, got -1$")


@pytest.mark.parametrize("size", ["3", "100000"])
def test_cli_gallery_size_out_of_range(capsys, no_work, tmp_path, size):
    _usage_error(capsys, ["gallery", "--out", str(tmp_path), "--size", size],
                 rf"--size must be in \[8, 8192\], got {size}$")


def test_cli_good_arguments_reach_the_work(monkeypatch, tmp_path):
    """The checks pass good arguments through (so the tests above can fail)."""
    seen = []
    monkeypatch.setattr(cli, "_gallery", lambda args: seen.append(args.out) or 0)
    assert cli.main(["gallery", "--out", str(tmp_path / "new"), "--names", "sphere"]) == 0
    assert seen == [str(tmp_path / "new")] and (tmp_path / "new").is_dir()


def test_cli_os_error_while_working_is_one_line(monkeypatch, capsys, tmp_path):
    def full_disk(args):
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(cli, "_gallery", full_disk)
    assert cli.main(["gallery", "--out", str(tmp_path)]) == 1
    assert capsys.readouterr().err == ("jaxiso gallery: error: [Errno 28] No space left on "
                                       "device\n")

