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
