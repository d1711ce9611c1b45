"""Bad input to scenes, `intersect`, `render`, cameras, lights and shading: a clear error
that names the value, never a wrong picture. Mirrors the probe list of issue 12 (the data
layer's probes are in test_bad_input_data.py, the arithmetic's in test_bad_input_arith.py).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxiso as ji
from jaxiso.implicit import csg
from jaxiso.volume import OctreeVolume, VolumeIsosurface


def sphere(x, y, z):
    return x * x + y * y + z * z - 1.0


BOX = dict(lo=(-1.5,) * 3, hi=(1.5,) * 3)
S = ji.ImplicitSurface(sphere, **BOX)
CAM = ji.Camera.look_at((3.0, 2.0, 1.5), (0, 0, 0), (0, 0, 1), 40.0, 8, 8)
METHODS = ("t-bisection", "k-bisection", "mitchell", "sampling", "sphere")


@pytest.mark.parametrize("eps", [-1.0, 0.0, np.nan, np.inf])
@pytest.mark.parametrize("method", ["t-bisection", "k-bisection", "mitchell"])
def test_eps_must_be_a_finite_positive_length(eps, method):
    # the probe: eps=-1 | nan | inf gave 676 hits instead of 268, no error
    with pytest.raises(ValueError, match=r"eps must be a finite positive length, got"):
        S.replace(method=method, eps=eps)
    with pytest.raises(ValueError, match=r"eps must be a finite positive"):
        ji.ImplicitSurface(sphere, **BOX, eps=eps, method=method)


def test_options_are_not_keywords_of_intersect_or_render():
    # options live on the scene: a misspelled or misplaced one is a TypeError
    with pytest.raises(TypeError, match="eps"):
        ji.render(S, CAM, eps=2.0**-9)
    with pytest.raises(TypeError, match="max_step"):
        ji.intersect(S, CAM.rays(), max_step=0)
    with pytest.raises(TypeError, match="arithmatic"):
        S.replace(arithmatic="affine")
    with pytest.raises(TypeError, match="arithmatic"):
        ji.ImplicitSurface(sphere, **BOX, arithmatic="affine")


@pytest.mark.parametrize("iso", [[np.nan], [0.0, np.inf], [-np.inf]])
def test_implicit_isovalues_must_be_finite(iso):
    with pytest.raises(ValueError, match=r"isovalues must be finite"):
        S.with_isovalues(iso)
    with pytest.raises(ValueError, match=r"isovalues must be finite"):
        ji.ImplicitSurface(sphere, **BOX, isovalues=iso)


@pytest.mark.parametrize("w", [np.nan, np.inf])
def test_w_must_be_finite(w):
    with pytest.raises(ValueError, match=r"w must be finite"):
        S.replace(w=w)


def test_params_must_be_finite():
    def blob(x, y, z, params):
        return x * x + y * y + z * z - params["r"][0] ** 2

    ok = ji.ImplicitSurface(blob, **BOX, params={"r": np.array([1.0, 2.0])})
    with pytest.raises(ValueError, match=r"params\['r'\] must be finite: 1 NaN or inf"):
        ok.replace(params={"r": np.array([1.0, np.nan])})
    ok.replace(params={"r": np.array([0.5, 2.0]), "n": np.int32(3)})  # ints pass


def test_delta_and_lipschitz_are_checked():
    with pytest.raises(ValueError, match=r"delta must be >= 0"):
        S.replace(delta=-1.0)
    with pytest.raises(ValueError, match=r"delta must be finite"):
        S.replace(delta=np.nan)
    with pytest.raises(ValueError, match=r"lipschitz"):
        S.replace(method="sphere")
    with pytest.raises(ValueError, match=r"lipschitz must be positive"):
        S.replace(method="sphere", lipschitz=0.0)


def test_volume_clip_box_must_be_finite():
    vol = OctreeVolume.from_array(np.random.default_rng(0).uniform(-1, 1, (5, 5, 5))
                                  .astype(np.float32))
    with pytest.raises(ValueError, match=r"clip_box must be finite"):
        VolumeIsosurface(vol, 0.0, clip_box=((np.nan, 0, 0), (1, 1, 1)))
    scene = VolumeIsosurface(vol, 0.0)
    with pytest.raises(ValueError, match=r"clip_lo must be finite"):
        scene.replace(clip_lo=jnp.array([np.nan, 0.0, 0.0]))
    with pytest.raises(ValueError, match=r"isovalues must be finite"):
        scene.with_isovalues([np.nan])


@pytest.mark.parametrize("vector", [(0.0, 0.0, 0.0), (np.nan, 0.0, 1.0), (np.inf, 1, 1)])
def test_light_needs_a_finite_nonzero_direction(vector):
    # the probe: NaN pixels, and save_png wrote them
    with pytest.raises(ValueError, match=r"Light vector|nonzero direction"):
        ji.Light(vector)


def test_point_light_may_sit_at_the_origin_but_not_at_nan():
    img = ji.render(S, CAM, light=ji.Light((0.0, 0.0, 0.0), point=True))
    assert np.all(np.isfinite(img))          # a light inside the sphere: dark, not NaN
    with pytest.raises(ValueError, match=r"Light vector must be finite"):
        ji.Light((np.nan, 0.0, 0.0), point=True)


def test_save_png_refuses_nan(tmp_path):
    img = np.full((4, 4, 3), 0.5, np.float32)
    img[1, 2, 0] = np.nan
    with pytest.raises(ValueError, match=r"1 NaN or inf values"):
        ji.save_png(img, tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()


@pytest.mark.parametrize("half", [1e9, 1e30])
def test_huge_domain_box_is_refused_with_a_hint(half):
    # the probe: depth capped at 30 without a word; the sphere drew twice as large at
    # +-1e9 and vanished at +-1e30
    with pytest.raises(ValueError, match=r"use eps >= "):
        ji.ImplicitSurface(sphere, (-half,) * 3, (half,) * 3)


def test_huge_domain_box_works_at_a_reachable_eps():
    # the message's bound is enough: at that eps the scene builds and traces
    with pytest.raises(ValueError, match=r"use eps >= ([0-9.e+]+)") as err:
        ji.ImplicitSurface(sphere, (-1e6,) * 3, (1e6,) * 3)
    eps = float(err.value.args[0].split("use eps >= ")[1].split(",")[0]) * 1.01
    big = ji.ImplicitSurface(lambda x, y, z: x * x + y * y + z * z - 1e10,
                             (-1e6,) * 3, (1e6,) * 3, eps=eps)
    cam = ji.Camera.look_at((3e5, 2e5, 1.5e5), (0, 0, 0), (0, 0, 1), 40.0, 8, 8)
    hits = ji.intersect(big, cam.rays())
    assert np.asarray(hits.hit).sum() > 10


def test_domain_box_diagonal_overflowing_float32():
    with pytest.raises(ValueError, match=r"overflows float32"):
        ji.ImplicitSurface(sphere, (-3e38,) * 3, (3e38,) * 3)


def test_shading_needs_at_least_one_colour():
    with pytest.raises(ValueError, match=r"colors must be \[C, 3\] with C >= 1"):
        ji.Shading(colors=np.zeros((0, 3)))
    with pytest.raises(ValueError, match=r"opacity must be in \[0, 1\]"):
        ji.Shading(opacity=1.5)
    with pytest.raises(ValueError, match=r"Shading background must be finite"):
        ji.Shading(background=(np.nan, 1.0, 1.0))


def test_unknown_method_lists_all_five():
    with pytest.raises(ValueError, match=r"method must be one of") as err:
        S.replace(method="bogus")
    for m in METHODS:
        assert m in str(err.value)
    with pytest.raises(ValueError, match=r"method must be one of \('t-bisection', "
                                         r"'k-bisection'\), got 'mitchell'"):
        csg.CSG(csg.union(sphere, lambda x, y, z: x - 0.5), **BOX, method="mitchell")


@pytest.mark.parametrize("width", [2.7, 0, -3, True, "8"])
def test_camera_size_must_be_a_whole_positive_number(width):
    # the probe: width=2.7 silently became 2
    with pytest.raises(ValueError, match=r"width must be a positive whole number"):
        ji.Camera.look_at((3, 2, 1), (0, 0, 0), (0, 0, 1), 40.0, width)
    assert ji.Camera.look_at((3, 2, 1), (0, 0, 0), (0, 0, 1), 40.0, 8.0).width == 8


def test_static_options_are_checked():
    for name, bad in (("max_steps", 0), ("max_steps", 2.5), ("samples", 1),
                      ("refine_steps", -1), ("normals", -0.1), ("normals", "central")):
        with pytest.raises(ValueError, match=name):
            S.replace(**{name: bad})
    with pytest.raises(ValueError, match=r"rounding must be one of"):
        S.replace(rounding="up")
    with pytest.raises(ValueError, match=r"arithmetic must be one of"):
        S.replace(arithmetic="ia")


def test_plan_is_checked():
    for bad in (dict(tile=0), dict(tile=2.5), dict(lanes=0), dict(tile=True)):
        with pytest.raises(ValueError, match=r"Plan\.(tile|lanes)"):
            ji.Plan(**bad)
    with pytest.raises(TypeError, match=r"plan must be a jaxiso.Plan"):
        ji.intersect(S, CAM.rays(), plan=(4, None))
    with pytest.raises(ValueError, match=r"lanes run t-bisection only"):
        ji.intersect(S.replace(method="k-bisection"), CAM.rays(), plan=ji.Plan(4, 64))


def test_not_a_scene_or_not_rays():
    with pytest.raises(TypeError, match=r"expected a scene"):
        ji.intersect(sphere, CAM.rays())
    with pytest.raises(TypeError, match=r"rays must be jaxiso.Rays"):
        ji.intersect(S, (jnp.zeros((4, 3)), jnp.ones((4, 3))))
    with pytest.raises(TypeError, match=r"camera must be a jaxiso.Camera"):
        ji.render(S, CAM.rays())


def test_traced_values_are_not_checked_but_replace_under_jit_works():
    # under jit the values are unknown at trace time; replace must still build the scene
    @jax.jit
    def hits(eps):
        return ji.intersect(S.replace(eps=eps), CAM.rays()).hit.sum()

    assert int(hits(2.0**-9)) == int(ji.intersect(S.replace(eps=2.0**-9), CAM.rays())
                                      .hit.sum())
