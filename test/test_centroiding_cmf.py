"""Constrained matched filter: constraints, shift recovery, noise (NEA, CRB), reference modes."""

import numpy as np
import pytest

from lgs_wfs_ros.centroiding import crb, make_centroider, model_derivatives
from lgs_wfs_ros.centroiding.cmf import design, solve_filter
from lgs_wfs_ros.centroiding.reference import fourier_derivatives, fourier_shift, integer_shift
from lgs_wfs_ros.optics import geometry
from lgs_wfs_ros.sensor import Sensor
from spotgen import sodium_line, spots
from pupils import SMALL

SENSOR = Sensor()
LAY = geometry.layout(SENSOR)
N = LAY.n_valid
CORE = 1.19 / 2.3548


def elongated_model(sigma=CORE, length=3.0, photons=1000.0, e=None):
    """``image_at(shift)`` for spots along e (detector axes) with a sodium line."""
    off, w = sodium_line(length, 11) if length else ((0.0,), None)
    e = LAY.e if e is None else e
    return lambda sh: spots(sh, sigma=sigma, e=e, offsets=off, weights=w, photons=photons)


def static_cmf(image_at, sensor=SENSOR, exact_derivatives=True, **options):
    options.setdefault("weighting", "model")
    options.setdefault("linearize", False)
    c = make_centroider("cmf", sensor, reference="static", **options)
    model, dx, dy = model_derivatives(image_at, geometry.layout(sensor).n_valid, h=1e-4)
    if exact_derivatives:
        c.set_reference(model, dx, dy)
    else:
        c.set_reference(model)
    return c, model, dx, dy


@pytest.mark.parametrize("constrained", [True, False])
@pytest.mark.parametrize("weighting", ["model", "image"])
def test_filter_satisfies_constraints(constrained, weighting):
    rng = np.random.default_rng(0)
    c, model, _, _ = static_cmf(elongated_model(), constrained=constrained, weighting=weighting)
    c.centroid(rng.poisson(model))
    r, ok, _ = c._filter(rng.poisson(model).astype(float).reshape(N, -1))
    assert ok.all()
    assert np.abs(r @ c.A - c.M).max() < 1e-9
    assert c.A.shape == (N, 256, 7 if constrained else 3)


def test_solve_filter_is_the_minimum_variance_solution():
    """R = M (A^T W A)^-1 A^T W: any other filter with R A = M has more variance."""
    rng = np.random.default_rng(1)
    a = rng.normal(size=(1, 256, 7))
    m = rng.normal(size=(2, 7))
    var = rng.uniform(1, 5, (1, 256))
    r, ok = solve_filter(a, m, var)
    assert ok.all() and np.abs(r @ a - m).max() < 1e-9
    # perturb within the null space of A^T: still R' A = M, larger variance
    q, _ = np.linalg.qr(a[0], mode="complete")
    null = q[:, 7:]
    r2 = r[0] + rng.normal(size=(2, 249)) @ null.T
    assert np.abs(r2 @ a[0] - m).max() < 1e-9
    v = lambda rr: np.einsum("kp,p,kp->k", rr, var[0], rr)
    assert (v(r2) > v(r[0])).all()


def test_fourier_dither_derivative_and_shifts():
    """The Fourier dither derivative equals the exact derivative for a well-sampled spot
    (1.5 % at sigma = 1 px) and the whole-pixel shift is exact."""
    img = spots([0.2, -0.1], sigma=1.5)
    h = 1e-4
    exact = (spots([0.2 + h, -0.1], sigma=1.5) - spots([0.2 - h, -0.1], sigma=1.5)) / (2 * h)
    gx, gy = fourier_derivatives(img, 0.02)
    assert np.abs(gx - exact).max() < 0.003 * np.abs(exact).max()
    lit = (fourier_shift(img, [0.02, 0]) - fourier_shift(img, [-0.02, 0])) / 0.04
    np.testing.assert_allclose(gx, lit, atol=1e-9 * np.abs(gx).max())
    np.testing.assert_allclose(integer_shift(img, 1, 0), spots([1.2, -0.1], sigma=1.5), atol=1e-3)
    np.testing.assert_allclose(fourier_shift(img, [1, 0]), np.roll(img, 1, axis=2), atol=1e-9)


def test_noise_free_shift_recovery():
    """CMF returns the imposed shift to 1e-3 px near the centre and exactly at the +-1 px
    constraint points; between them its nonlinearity stays small and is reported here."""
    image_at = elongated_model(sigma=CORE, length=3.0)
    c, *_ = static_cmf(image_at)
    # small shifts (measured max error: 6e-4 px at +-0.15, 1.3e-3 at +-0.2, 4.4e-3 at +-0.3)
    rng = np.random.default_rng(2)
    small = rng.uniform(-0.15, 0.15, (N, 2))
    np.testing.assert_allclose(c.centroid(image_at(small)), small, atol=1e-3)
    # 1-D shifts along a pixel axis up to 0.2 px
    sh = np.zeros((N, 2))
    sh[:, 0] = np.linspace(-0.2, 0.2, N)
    np.testing.assert_allclose(c.centroid(image_at(sh)), sh, atol=1e-3)
    # constraint points: exactly +-1 px along x and along y
    for d in ([1, 0], [-1, 0], [0, 1], [0, -1]):
        sh = np.tile(d, (N, 1)).astype(float)
        np.testing.assert_allclose(c.centroid(image_at(sh)), sh, atol=1e-9)
    # anywhere in +-1 px (2-D): the linear filter's nonlinearity is bounded but not small
    # (measured: 0.017 px at +-0.5, 0.19 px in the +-1 px corners for this 1.19 px core)
    big = rng.uniform(-0.5, 0.5, (N, 2))
    assert np.abs(c.centroid(image_at(big)) - big).max() < 0.03
    big = rng.uniform(-1, 1, (N, 2))
    assert np.abs(c.centroid(image_at(big)) - big).max() < 0.3


def test_linearized_cmf_exact_within_one_pixel():
    """With its response calibrated and inverted (linearize=True) the CMF returns any
    imposed shift within +-1 px (2-D, corners included) to 1e-3 px, and its NEA is the
    raw NEA mapped through the inverse response (unchanged at the centre)."""
    image_at = elongated_model(sigma=CORE, length=3.0)
    c, *_ = static_cmf(image_at, linearize=True)
    raw, *_ = static_cmf(image_at)
    off = np.full((N, 2), 0.5)
    # a static reference never calibrated gives the raw filter's estimate
    np.testing.assert_array_equal(c.centroid(image_at(off)), raw.centroid(image_at(off)))
    assert c.calibrate_response(image_at) < 1e-3          # fit residual of the response, px
    rng = np.random.default_rng(5)
    for box in (0.15, 0.5, 1.0):
        sh = rng.uniform(-box, box, (N, 2))
        np.testing.assert_allclose(c.centroid(image_at(sh)), sh, atol=1e-3)
    corners = np.array([[1, 1], [-1, 1], [1, -1], [-1, -1]], float)[rng.integers(0, 4, N)]
    np.testing.assert_allclose(c.centroid(image_at(corners)), corners, atol=1e-3)
    # at the centre the response is the identity: same NEA as the raw filter
    raw, *_ = static_cmf(image_at)
    x = image_at(np.zeros((N, 2)))
    raw.centroid(x)
    c.centroid(x)
    np.testing.assert_allclose(c.nea, raw.nea, rtol=1e-2)
    # a reference change invalidates the calibration; it is redone with the kept image_at
    c.set_reference(image_at(np.zeros((N, 2))))
    np.testing.assert_allclose(c.centroid(image_at(sh)), sh, atol=0.02)


@pytest.mark.parametrize("detector", ["polar", "cartesian"])
def test_linearized_model_reference_calibrates_itself(detector):
    """reference='model' scans its own model images: exact on them over +-1 px; the
    history reference changes every frame, so linearize does not apply to it."""
    s = Sensor.paper_single(detector)
    c = make_centroider("cmf", s, reference="model", weighting="model", linearize=True)
    n = c.n
    rng = np.random.default_rng(6)
    sh = rng.uniform(-1, 1, (200, n, 2))
    est = np.stack([c.to_pixel_axes(c.centroid(c.model_images(10e3, v))) for v in sh])
    assert np.abs(est - sh).max() < 1e-3
    raw = make_centroider("cmf", s, reference="model", weighting="model", linearize=False)
    err_raw = np.stack([raw.to_pixel_axes(raw.centroid(c.model_images(10e3, v))) for v in sh]) - sh
    assert np.abs(err_raw).max() > 0.02                  # what the linearisation removed
    assert "linearize" in c.describe()
    hist = make_centroider("cmf", s, reference="history", linearize=True)
    assert not hist.linearize and "linearize" not in hist.describe()
    assert hist.weighting == "image"                      # auto: the paper's with a history
    with pytest.raises(ValueError, match="linearize must be"):
        make_centroider("cmf", s, reference="model", linearize="yes")


def test_fourier_derivative_well_sampled_spot_to_1e3():
    """With the Fourier dither (no derivative images given) a well-sampled spot is fine."""
    image_at = elongated_model(sigma=1.0, length=2.0)
    c, *_ = static_cmf(image_at, exact_derivatives=False)
    small = np.random.default_rng(3).uniform(-0.15, 0.15, (N, 2))
    np.testing.assert_allclose(c.centroid(image_at(small)), small, atol=1e-3)


def test_fourier_derivative_undersampled_core_has_gain_error():
    """Documented limitation: for the 1.19 px core the Fourier dither underestimates the
    derivative, so the cross-elongation gain is off by tens of percent."""
    image_at = elongated_model(sigma=CORE, length=0.0)
    c, *_ = static_cmf(image_at, exact_derivatives=False)
    sh = np.full((N, 2), 0.05)
    gain = c.centroid(image_at(sh)) / 0.05
    assert 0.4 < np.median(gain) < 0.9


@pytest.mark.parametrize("detector", ["cartesian", "polar"])
def test_measured_error_matches_predicted_nea(detector):
    """Stationary Poisson spots (1000 photons), model weighting: std within 10 % of NEA."""
    sensor = SENSOR.replace(detector=detector)
    e = np.tile([1.0, 0.0], (N, 1)) if detector == "polar" else LAY.e
    image_at = elongated_model(sigma=CORE, length=3.0, e=e)
    c, model, _, _ = static_cmf(image_at, sensor=sensor)
    rng = np.random.default_rng(4)
    outs, neas = [], []
    for _ in range(3):
        outs.append(c.centroid(rng.poisson(model)))
        neas.append(np.einsum("nii->ni", c.nea))
    outs, neas = np.array(outs), np.array(neas)
    measured = np.sqrt(np.mean(outs ** 2, axis=(0, 1)))
    predicted = np.sqrt(np.mean(neas, axis=(0, 1)))
    np.testing.assert_allclose(measured, predicted, rtol=0.10)
    # full covariance too (cartesian: x/y correlated through e)
    cov = np.einsum("fni,fnj->ij", outs, outs) / (outs.shape[0] * N)
    np.testing.assert_allclose(cov, np.nanmean(c.nea, axis=0), atol=0.1 * predicted.max() ** 2)


def test_image_weighting_nea_is_optimistic_by_about_ten_percent():
    """The paper's image weighting: the prediction from the noisy image underestimates the
    real error (weights correlate with the noise); documented, checked to 20 %."""
    image_at = elongated_model(sigma=CORE, length=3.0)
    c, model, _, _ = static_cmf(image_at, weighting="image")
    rng = np.random.default_rng(5)
    out = c.centroid(rng.poisson(model))
    measured = np.sqrt(np.mean(out ** 2))
    predicted = np.sqrt(np.mean(np.einsum("nii->ni", c.nea)))
    assert 1.0 < measured / predicted < 1.2


def test_cmf_within_20_percent_of_crb_round_gaussian():
    """Round Gaussian spot, 1000 photons: Monte-Carlo CMF error within 20 % of the CRB."""
    image_at = elongated_model(sigma=1.0, length=0.0)
    c, model, dx, dy = static_cmf(image_at)
    bound = crb(model, dx, dy)
    rng = np.random.default_rng(6)
    out = np.concatenate([c.centroid(rng.poisson(model)) for _ in range(2)])
    measured = np.sqrt(np.mean(out ** 2, axis=0))
    ratio = measured / np.sqrt(np.mean(bound ** 2, axis=0))
    assert (ratio < 1.2).all() and (ratio > 0.9).all()
    # and the CRB here is about sigma/sqrt(N) (pixels of 1 sigma add a little)
    assert abs(np.median(bound) / (1.0 / np.sqrt(1000)) - 1) < 0.1


def test_history_reference_paper_semantics():
    """History mode: the reference is the mean of the last 5 frames; a stationary spot reads
    ~0 whatever its offset (reference taken as centred), a jump reads as a displacement."""
    image_at = elongated_model(sigma=1.0, length=2.0)
    c = make_centroider("cmf", SENSOR, reference="history")  # the paper's CMF
    assert c.options["history"] == 5 and c.weighting == "image" and not c.linearize
    off = image_at(np.full((N, 2), 0.4))
    for _ in range(6):
        out = c.centroid(off)
    np.testing.assert_allclose(out, 0, atol=1e-9)
    np.testing.assert_allclose(c.reference, off, atol=1e-9)
    # a 0.1 px jump: the current frame is 1/5 of the new reference
    jump = image_at(np.full((N, 2), 0.5))
    out = c.centroid(jump)
    assert np.all(np.abs(out - 0.08) < 0.01)
    # include_current=False: the reference is the earlier frames only
    c2 = make_centroider("cmf", SENSOR, reference="history", include_current=False)
    for _ in range(5):
        c2.centroid(off)
    out2 = c2.centroid(jump)
    np.testing.assert_allclose(out2, 0.1, atol=2e-3)
    # reset() forgets the history
    c2.reset()
    assert c2.reference is None
    np.testing.assert_allclose(c2.centroid(jump), 0, atol=1e-9)


def test_update_period_and_static_reference_requirements():
    image_at = elongated_model(sigma=1.0, length=2.0)
    c = make_centroider("cmf", SENSOR, reference="history", update_period=3, include_current=False)
    a, b = image_at(np.zeros((N, 2))), image_at(np.full((N, 2), 0.1))
    c.centroid(a)                   # frame 0: reference <- a
    first = c.reference
    c.centroid(b)
    c.centroid(b)
    np.testing.assert_array_equal(c.reference, first)       # not refreshed at frames 1, 2
    c.centroid(b)                                           # frame 3: refreshed
    np.testing.assert_allclose(c.reference, (a + b + b) / 3)
    s = make_centroider("cmf", SENSOR, reference="static")
    with pytest.raises(ValueError, match="set_reference"):
        s.centroid(a)
    with pytest.raises(ValueError, match="shape"):
        s.set_reference(a[:10])
    s.set_reference(a)
    s.reset()                                               # keeps an installed static reference
    assert np.isfinite(s.centroid(b)).all()


def test_model_reference_needs_no_images():
    """reference="model": built from the sensor (core + 10 km layer), usable at once (a 30 x
    30 pupil of 1 m subapertures: the full pupil's radii, a quarter of its blocks)."""
    c = make_centroider("cmf", SMALL, reference="model", weighting="model")
    model = c.reference
    out = c.centroid(model)
    np.testing.assert_allclose(out, 0, atol=1e-9)
    assert np.isfinite(out).all()


def test_background_and_read_noise_weighting():
    """With background/read noise, model weighting still predicts its error (NEA)."""
    s = SENSOR.replace(read_noise_e=3.0, background_e=2.0)
    image_at = elongated_model(sigma=CORE, length=3.0)
    model, dx, dy = model_derivatives(image_at, N, h=1e-4)
    c = make_centroider("cmf", s, reference="static", weighting="model")
    c.set_reference(model + 2.0, dx, dy)
    rng = np.random.default_rng(7)
    frame = rng.poisson(model + 2.0) + rng.normal(0, 3.0, model.shape)
    out = c.centroid(frame)
    measured = np.sqrt(np.mean(out ** 2))
    predicted = np.sqrt(np.mean(np.einsum("nii->ni", c.nea)))
    assert abs(measured / predicted - 1) < 0.1
    bound = crb(model, dx, dy, read_noise_e=3.0, background_e=2.0)
    assert measured < 1.3 * np.sqrt(np.mean(bound ** 2))


def test_design_columns():
    t = spots([0, 0], sigma=1.0, n=2)
    a, m = design(t)
    assert a.shape == (2, 256, 7) and m.shape == (2, 7)
    np.testing.assert_allclose(a[..., 3].reshape(2, 16, 16), integer_shift(t, 1, 0))
    a3, m3 = design(t, constrained=False)
    assert a3.shape == (2, 256, 3)
    np.testing.assert_array_equal(m3, [[1, 0, 0], [0, 1, 0]])


def test_pushed_dither_images_give_exact_gain_on_the_undersampled_core():
    """derivative="dither" (the paper's dithered images, averaged): with noise-free
    dithers of the real spot the 1.19 px core has the right gain, unlike the Fourier
    derivative of the reference."""
    image_at = elongated_model(sigma=CORE, length=3.0)
    c = make_centroider("cmf", SENSOR, reference="history", derivative="dither", weighting="model")
    with pytest.raises(ValueError, match="push_dither"):
        c.centroid(image_at(np.zeros((N, 2))))
    c.reset()
    d = 0.02
    z = np.zeros((N, 2))
    dith = np.stack([image_at(z + [d, 0]), image_at(z - [d, 0]), image_at(z + [0, d]), image_at(z - [0, d])])
    for _ in range(5):                           # history of centred frames and their dithers
        c.push_dither(dith)
        c.centroid(image_at(z))
    # the next frame moved a little: the reference (with it) is mostly the centred spot
    sh = np.full((N, 2), 0.05)
    c.push_dither(dith)
    out = c.centroid(image_at(sh))
    np.testing.assert_allclose(out, sh * 4 / 5, atol=1.5e-3)   # 1/5 of the move is in the reference
    assert "pushed dithered" in c.describe()["derivative"]
    with pytest.raises(ValueError, match="dither images"):
        c.push_dither(dith[:2])


def test_a_model_weighted_filter_is_built_with_the_centroider_not_on_its_first_frame(monkeypatch):
    """A live node builds its centroider when the sensor description arrives; the filter
    (~0.2 s for the full pupil) must be ready then, not solved on the first frame."""
    from lgs_wfs_ros.centroiding import cmf as cmf_module

    sensor = Sensor(diameter_m=4.0, obstruction_m=0.5, n_subaps=8)
    cmf = make_centroider("cmf", sensor, reference="model", weighting="model", linearize=False)

    def no_solve(*args, **kwargs):
        raise AssertionError("a filter solved on the frame path")

    monkeypatch.setattr(cmf_module, "solve_filter", no_solve)
    frame = np.random.default_rng(1).poisson(30, sensor.frame_shape).astype(np.uint16)
    assert np.isfinite(cmf.centroid(frame)).all()
