"""The binomial noise of merged binary frames: the variance-stabilising transform."""

import numpy as np


def test_stabilised_detections_have_the_same_noise_at_every_flux():
    """Anscombe's arcsine transform: the variance of n binary frames' detection fraction is 1/(4n) at any flux."""
    from photonpano.binomial import binary_exposure, stabilised_detections
    from photonpano.photons import flux_mle

    rng = np.random.default_rng(3)
    tau, n = 1e-5, 400
    spread = {}
    for mean in (0.05, 0.5, 2.0, 4.0):  # per pixel per frame: detection probability 0.05 to 0.98
        counts = rng.binomial(n, 1 - np.exp(-mean), size=20_000).astype(np.float32)
        flux = flux_mle(counts, float(n), tau)
        spread[mean] = (np.var(stabilised_detections(flux, tau)) * 4 * n, np.var(flux * tau))
    for stabilised, _ in spread.values():
        assert 0.85 < stabilised < 1.2, spread  # 1/(4n), within the transform's small-n bias
    assert spread[4.0][1] > 100 * spread[0.05][1]  # the flux MLE's variance grows with the flux
    assert np.isnan(stabilised_detections(np.array([np.nan, 1e5]), tau)[0])
    assert binary_exposure(type("Video", (), {"kind": "intensity", "exposure_s": 1e-3})()) is None
    assert binary_exposure(type("Spad", (), {"kind": "binary", "exposure_s": 1e-5})()) == 1e-5


def test_stabilised_detections_follow_the_exact_transform_to_float32_precision():
    """The compiled table is the transform arcsin(sqrt(1 - exp(-x))) computed in float64, to a float32 step.

    numpy's float32 form is off by up to 2.5e-4 near saturation (1 - exp(-x) rounds to 1 in
    float32 beyond x = 16.6, where the transform is still 1.7e-4 under pi/2); the table is not.
    """
    from photonpano.binomial import stabilised_detections

    tau = 1e-5
    flux = np.concatenate([np.linspace(0, 5e6, 200_000), [1e-3, 1.0, 3.6e6, 3.7e6, 1e9, 3e38, 2e38]]).astype(np.float32)
    exact = np.arcsin(np.sqrt(-np.expm1(-flux.astype(np.float64) * np.float32(tau))))
    found = stabilised_detections(flux.reshape(3, -1), tau)
    assert found.dtype == np.float32 and found.shape == (3, len(flux) // 3)
    assert np.abs(found.reshape(-1) - exact).max() < 1.2e-7  # one float32 step at pi/2
    assert (found.reshape(-1)[-2:] == np.float32(np.pi / 2)).all()
    odd = stabilised_detections(np.array([np.nan, np.inf, -np.inf, -4.0, 0.0], np.float32), tau)
    assert np.isnan(odd[:3]).all() and (odd[3:] == 0).all()
