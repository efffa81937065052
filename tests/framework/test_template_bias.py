"""The mosaic template's own error, modelled and taken out of the registrations (photonpano.schemes.template_bias)."""

import numpy as np
import pytest
from photonpano import geometry
from photonpano.executor import SerialExecutor
from photonpano.host import PluginHost
from photonpano.metrics import trajectory_error
from photonpano.schemes import LevelTask, MosaicScheme
from photonpano.schemes.template_bias import knot_weights, template_displacement
from photonpano.spec import validate_spec

HOST = PluginHost()


def _pan(frames: int, speed: float) -> np.ndarray:
    """(T, 3, 3) frame-to-canvas translations of a pan along x."""
    h = np.repeat(np.eye(3)[None], frames, axis=0)
    h[:, 0, 2] = 10 + speed * np.arange(frames)
    h[:, 1, 2] = 5
    return h


def test_knot_weights_interpolate_linearly_and_sum_to_one():
    knots = np.array([0.0, 10.0, 30.0])
    w = knot_weights(np.array([0.0, 5.0, 10.0, 20.0, 30.0, 40.0]), knots)
    np.testing.assert_allclose(w, [[1, 0, 0], [0.5, 0.5, 0], [0, 1, 0], [0, 0.5, 0.5], [0, 0, 1], [0, 0, 1]])


def test_a_shift_every_frame_shares_displaces_the_template_by_that_shift():
    """Frames that all sit 0.3 px right and 0.1 px down of their estimate make a template shifted by just that.

    The model's template displacement (the frame-weighted mean of the frames' displacements)
    of a common frame-side shift ``p5 = 0.3, p6 = 0.1`` is that shift at every cell a frame
    sees, whatever the knot, and zero where none does.
    """
    width, height = 64, 32
    homographies = _pan(2000, 0.05)
    knots = np.linspace(0, 1999, 5)
    xs, ys = np.meshgrid(np.arange(0.0, 220.0, 8.0), np.arange(0.0, 48.0, 8.0))
    displacement, frames = template_displacement(homographies, xs.ravel(), ys.ravel(), knots, width, height)
    a = np.zeros((len(knots), 8))
    a[:, 4], a[:, 5] = 0.3, 0.1
    d = (displacement @ a.ravel()).reshape(-1, 2)
    seen = frames > 0
    assert 0 < seen.mean() < 1  # the canvas reaches past the pan on both axes
    np.testing.assert_allclose(d[seen], np.tile([0.3, 0.1], (int(seen.sum()), 1)), atol=1e-12)
    assert np.all(d[~seen] == 0)
    # a rotation error of the frames displaces the template's cells about each frame's own centre
    a = np.zeros((len(knots), 8))
    a[:, 2], a[:, 1] = -0.001, 0.001  # x' = x - 0.001 y, y' = y + 0.001 x about the frame centre
    d = (displacement @ a.ravel()).reshape(-1, 2)
    assert np.abs(d[seen]).max() < 0.001 * np.hypot(width, height) / 2 + 1e-12


@pytest.fixture(scope="module")
def drifting_estimate():
    """A 6 000-frame pan (flux 0.5) and an estimate that drifts from the truth smoothly, 0.6 px at the ends."""
    spec = validate_spec({"source": {"plugin": "simulate", "frames": 6000,
                                     "speed_px_per_frame": 0.03, "vibration_px": 0.0, "flux": 0.5, "seed": 3}},
                         HOST)
    source = spec.source.build()
    truth = source.ground_truth
    t = np.linspace(-1, 1, source.n_frames)
    error = np.zeros((source.n_frames, 8))
    error[:, 4] = 0.6 * t  # the frame centre drifts along the pan
    error[:, 2], error[:, 1] = -0.002 * t ** 2, 0.002 * t ** 2  # and rolls
    centre = geometry.translation((source.width - 1) / 2, (source.height - 1) / 2)
    estimate = geometry.normalize(truth @ centre @ geometry.homographies_from_params(error) @ np.linalg.inv(centre))
    return spec, source, estimate


def _level_error(spec, source, estimate, correct: bool, per_parameter: bool = False,
                 affine: bool = False, located: list | None = None) -> tuple[float, dict | None]:
    """RMSE (px, after global alignment) of the keyframes one mosaic level registers, and its record.

    ``affine``: the level registers affine corrections (``mosaic.perspective_levels``);
    ``located``: gets the level's :class:`~photonpano.schemes.LocateResult`.
    """
    m = 300
    groups = spec.resampler.build().groups(source.n_frames, m, 2)
    affine_locator = spec.mosaic.locator.model_copy(update={"motion": "affine"}).build if affine else None
    scheme = MosaicScheme(spec.mosaic.locator.build, spec.mosaic.template.build, correct_bias=correct,
                          per_parameter_priors=per_parameter, make_affine_locator=affine_locator,
                          affine_from_level=2 if affine else None)
    task = LevelTask(2, source, spec.merger.build(), groups, estimate, m, SerialExecutor())
    result = scheme.locate(task)
    if located is not None:
        located.append(result)
    found = trajectory_error(result.keyframes, source.ground_truth[groups.reference], source.width, source.height)
    return found.rmse_px, result.template_bias


def test_the_correction_takes_the_template_s_share_out_of_a_mosaic_level(drifting_estimate):
    """Against a template made with a drifting estimate, a level corrects only part of the drift; corrected, most.

    The estimate drifts along the pan by up to 0.6 px and rolls (0.369 px RMSE after global
    alignment); one mosaic level's keyframes keep 0.164 px of it against the plain template
    (the frames that see the same canvas share their drift) and 0.068 px once each
    registration is corrected for the template's share (measured, 254x496 frames).
    """
    spec, source, estimate = drifting_estimate
    before = trajectory_error(estimate, source.ground_truth, source.width, source.height).rmse_px
    plain, none = _level_error(spec, source, estimate, correct=False)
    corrected, record = _level_error(spec, source, estimate, correct=True)
    assert none is None
    assert record is not None and record["knots"] >= 4 and record["correction_px"] > 0.05
    assert before > 0.3
    assert plain > before / 3  # the template's share is real
    assert corrected < plain / 2 and corrected < 0.1


def test_affine_registrations_are_corrected_on_their_own_parameters_and_stay_affine(drifting_estimate):
    """At an affine mosaic level the model projects the template's share on p1..p6, and the correction adds no keystone.

    The estimate's drift (a shift and a roll) is affine. Measured (254x496 frames): 0.050 px
    without the correction, 0.036 px with it. Fitted as if the registrations measured all 8
    parameters, their zero keystones read as measurements, the correction gave them
    keystones of its own, and the level ended at 0.310 px.
    """
    spec, source, estimate = drifting_estimate
    plain, _ = _level_error(spec, source, estimate, correct=False, affine=True)
    located: list = []
    corrected, record = _level_error(spec, source, estimate, correct=True, affine=True, located=located)
    assert record is not None and record["knots"] >= 4
    assert np.all(located[0].registrations.homographies[:, 2, :2] == 0.0)
    assert corrected < 0.8 * plain and corrected < 0.05, (plain, corrected)


def test_a_keystone_ramp_is_taken_out_by_a_level_with_a_prior_per_parameter(drifting_estimate):
    """An estimate whose keystone (p7) drifts along the pan: the level's priors single out p7 and remove the ramp.

    Measured (6 000 frames of the bundled photo): 0.378 px before, 0.118 px after the level
    with one prior for all 8 (0.093 px), 0.114 px with one each (p7's 0.35 px, the others
    0.005-0.017 px). On 20 000 frames of the astronaut the difference is larger: 0.188 and
    0.059 px (``benchmarks/convergence.py --mode perspective``).
    """
    spec, source, _ = drifting_estimate
    t = np.linspace(-1, 1, source.n_frames)
    error = np.zeros((source.n_frames, 8))
    error[:, 6] = 0.6 / ((source.width - 1) / 2) ** 2 * t  # 0.6 px at the frame's edges at the ends
    centre = geometry.translation((source.width - 1) / 2, (source.height - 1) / 2)
    estimate = geometry.normalize(source.ground_truth @ centre @ geometry.homographies_from_params(error)
                                  @ np.linalg.inv(centre))
    before = trajectory_error(estimate, source.ground_truth, source.width, source.height).rmse_px
    shared, shared_record = _level_error(spec, source, estimate, correct=True)
    each, record = _level_error(spec, source, estimate, correct=True, per_parameter=True)
    assert len(record["prior_px"]) == 8 and len(set(shared_record["prior_px"])) == 1
    priors = np.array(record["prior_px"])
    assert priors[6] > 5 * np.delete(priors, 6).max()
    assert each < before / 3 and shared < before / 3


def test_an_error_in_one_parameter_gets_its_own_prior_and_is_not_shrunk_by_the_others():
    """A keystone ramp (p7) among seven parameters without error: each parameter's own prior.

    One prior for all 8, set by the seven near zero, shrinks the ramp and lets the seven
    fit the noise (in a mosaic level, a keystone ramp injected into the truth was
    corrected by 0.42 of it with one prior, 0.82 with one per parameter).
    """
    from photonpano.schemes._template_bias_fit import corner_scale, fit_error

    rng = np.random.default_rng(3)
    width, height, n_knots, groups = 496, 254, 12, 48
    knots = np.linspace(0, 9999, n_knots)
    middles = np.linspace(100, 9899, groups)
    weights = knot_weights(middles, knots)  # (G, K)
    corner = corner_scale(width, height)
    truth = np.zeros((n_knots, 8))
    truth[:, 6] = np.linspace(-0.6, 0.6, n_knots) / corner[6]  # 0.6 px at the corners at the ends
    # registrations see their group's error (no template share), with 0.1 px of noise per parameter
    model = -np.einsum("gk,ij->gikj", weights, np.eye(8)).reshape(groups, 8, n_knots * 8)
    measured = model @ truth.ravel() + rng.normal(0.0, 0.1, (groups, 8)) / corner
    information = np.repeat(np.diag(1 / (0.1 / corner) ** 2)[None], groups, axis=0)
    fitted, priors = fit_error(model, measured, information, n_knots, width, height, per_parameter=True)
    fitted = fitted.reshape(n_knots, 8)
    slope = np.polyfit(knots, fitted[:, 6], 1)[0] / np.polyfit(knots, truth[:, 6], 1)[0]
    assert 0.85 < slope < 1.15  # one prior for all: 0.80
    others = np.delete(np.arange(8), 6)
    assert priors[6] > 3 * np.max(priors[others])
    assert np.sqrt(np.mean((fitted[:, others] * corner[others]) ** 2)) < 0.04  # one prior for all: 0.058
