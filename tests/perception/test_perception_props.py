"""Property tests: any input gives a finite (n_x, 3) SOI or BadCloud, never another exception."""

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import array_shapes, arrays

from bagit.common.errors import BadCloud
from bagit.common.geometry import points_to_polyline_distance
from bagit.services.perception import extract_soi
from bagit.services.perception.synthetic import rim_cloud, true_rim

SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def soi_or_bad_cloud(points: object, n_x: object, **kw: object) -> np.ndarray | None:
    try:
        soi = extract_soi(points, n_x, **kw)  # type: ignore[arg-type]
    except BadCloud as e:
        assert str(e) and "\n" not in str(e)  # a one-line reason
        return None
    assert soi.shape == (n_x, 3) and soi.dtype == np.float64 and np.all(np.isfinite(soi))
    return soi


@SETTINGS
@given(
    arrays(
        st.sampled_from([np.float64, np.float32, np.float16]),
        st.one_of(st.tuples(st.integers(0, 400), st.integers(0, 5)), array_shapes(min_dims=1, max_dims=3, min_side=0, max_side=8)),
        elements=st.floats(allow_nan=True, allow_infinity=True, width=16),
    ),
    st.integers(-2, 40),
)
def test_arbitrary_arrays_give_soi_or_bad_cloud(points, n_x):
    soi_or_bad_cloud(points, n_x)


@SETTINGS
@given(
    arrays(np.float64, st.tuples(st.integers(0, 400), st.just(3)), elements=st.floats(allow_nan=False, allow_infinity=False)),
    st.integers(4, 40),
)
def test_arbitrary_finite_clouds_tiny_to_huge_values(points, n_x):
    soi_or_bad_cloud(points, n_x)


@SETTINGS
@given(
    st.integers(0, 10_000),
    st.sampled_from([1e-9, 1e-4, 1e-2, 1.0, 1e3]),
    st.integers(4, 40),
)
def test_rescaled_rims_give_soi_or_bad_cloud(seed, scale, n_x):
    """Rims far smaller or larger than a bag (nanometres to kilometres) never crash."""
    rim = true_rim("ellipse", rpy=(0.2, 0.1, 0.3))
    cloud, _ = rim_cloud(rim, n_points=2000, seed=seed)
    soi_or_bad_cloud(cloud * scale, n_x)


@SETTINGS
@given(
    arrays(np.float64, st.tuples(st.integers(0, 6), st.integers(0, 4)), elements=st.floats(allow_nan=True, allow_infinity=True)),
)
def test_arbitrary_init_and_hint_give_soi_or_bad_cloud(junk):
    rim = true_rim("lens")
    cloud, _ = rim_cloud(rim, n_points=3000, seed=1)
    soi_or_bad_cloud(cloud, 6, init=junk)
    soi_or_bad_cloud(cloud, 6, start_hint=junk)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 10_000), st.floats(0.0, 0.4), st.floats(0.0, 0.2), st.integers(4, 48))
def test_random_rims_give_soi_near_the_rim_or_bad_cloud(seed, outliers, occlusion, n_x):
    rng = np.random.default_rng(seed)
    kind = str(rng.choice(["ellipse", "lens", "wavy", "sagging"]))
    rim = true_rim(kind, rpy=tuple(rng.uniform(-0.5, 0.5, 3)), aspect=float(rng.uniform(0.4, 1.0)))
    cloud, _ = rim_cloud(rim, n_points=int(rng.integers(200, 5000)), outlier_fraction=outliers, occlusion=occlusion, seed=seed)
    soi = soi_or_bad_cloud(cloud, n_x)
    if soi is not None:
        assert points_to_polyline_distance(soi, rim).max() < 0.05


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 10_000), st.floats(-0.05, 0.05), st.floats(-0.05, 0.05))
def test_warm_start_from_a_displaced_init_keeps_its_indexing(seed, dx, dy):
    """Whatever the previous SOI's offset (up to 5 cm), the result keeps init's cyclic order and direction."""
    rim = true_rim("ellipse", rpy=(0.1, 0.0, 0.3))
    cloud, _ = rim_cloud(rim, seed=seed)
    init = np.roll(extract_soi(cloud, 16), seed % 16, axis=0)[:: 1 if seed % 2 else -1] + [dx, dy, 0.0]
    soi = soi_or_bad_cloud(cloud, 16, init=init)
    assert soi is not None
    # Undo the displacement: point i is then the SOI point nearest init point i, up to one common
    # cyclic shift (the rim moved, so the phase may slide by a place) -- same order, same direction.
    back = init - [dx, dy, 0.0]
    nearest = np.argmin(np.linalg.norm(back[:, None] - soi[None], axis=2), axis=1)
    shift = (nearest - np.arange(16)) % 16
    spread = (shift - shift[0] + 8) % 16 - 8  # shifts relative to point 0's, in -8..7
    assert np.ptp(spread) <= 1, shift
