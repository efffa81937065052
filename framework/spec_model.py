"""The spec's pydantic model: the stage slots built from the plugins installed, and the method's settings.

:func:`spec_model` builds ``PipelineSpec`` for a plugin host (each stage slot a
discriminated union of the configs registered for it, so third-party plugins validate
exactly like built-ins); :func:`level_schemes` and :func:`plugin_configs` read a
validated spec. Reading YAML and reporting errors is :mod:`photonpano.spec`'s.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Any, Literal, Protocol, Union, cast

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    create_model,
    field_validator,
    model_validator,
)

from .errors import PluginError
from .host import PluginHost
from .spec_compat import move_refine_locator, move_scale
from .spec_defaults import DEFAULT_PLUGINS, MOSAIC_PLUGINS
from .stages import STAGES

if TYPE_CHECKING:
    from .stages import (
        CompositorConfig,
        InterpolatorConfig,
        LocatorConfig,
        MergerConfig,
        PoseEstimatorConfig,
        ResamplerConfig,
        SourceConfig,
    )

__all__ = ["OutputsConfig", "PipelineSpec", "MosaicSettings", "spec_model", "level_schemes", "plugin_configs"]


class OutputsConfig(BaseModel):
    """Which optional outputs to write besides homographies, panorama and run.json."""

    model_config = ConfigDict(extra="forbid", frozen=True, use_attribute_docstrings=True)

    panorama_png: bool = True
    """Write ``panorama.png``, the tone-mapped 16-bit sRGB panorama (with alpha: transparent where unobserved)."""
    merged_frames: bool = False
    """Write each level's merged frames as ``level_<k>/merged.npy`` (float32 flux) and PNGs,
    at every level."""
    trajectory_plot: bool = True
    """Write ``trajectory.png``, the estimated (and true, if known) frame centres."""
    report: bool = True
    """Write ``report.html``: one self-contained page (images inlined) with the status, warnings,
    panorama, trajectory, per-level figures, spec and versions."""
    video: bool = False
    """Write ``video.mp4``: the stabilised virtual exposures on the panorama canvas, as
    ``photonpano video`` renders them by default (needs the ``video`` extra, PyAV)."""


class MosaicSettings(Protocol):
    """The type of a spec's ``mosaic`` section (the model :func:`_mosaic_model` builds)."""

    locator: LocatorConfig
    template: CompositorConfig
    subbatch_px: float
    reject_movers: Literal["auto"] | float | None
    registration_binning: Literal["auto"] | int
    holdout: int
    correct_template_bias: bool
    template_bias_priors: Literal["shared", "per-parameter"]
    correct_shape_drift: bool
    perspective_levels: int | None


class _SpecBase(BaseModel):
    """The base of every ``PipelineSpec`` model :func:`spec_model` builds.

    The fields are added by :func:`spec_model` (the stage slots depend on the plugins
    installed); they are declared here for type checkers only, with the base class of
    each stage's configs.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, use_attribute_docstrings=True)

    if TYPE_CHECKING:
        version: Literal[1]
        source: SourceConfig
        resampler: ResamplerConfig
        merger: MergerConfig
        locator: LocatorConfig
        interpolator: InterpolatorConfig
        compositor: CompositorConfig
        pose_estimator: PoseEstimatorConfig | None
        mosaic: MosaicSettings
        levels: int
        group_size: Literal["auto"] | int
        pair_offsets: list[int]
        camera_model: Literal["auto", "homography"]
        registration_binning: Literal["auto"] | int
        hot_pixels: Literal["auto", "off"]
        panorama_subbatch_px: float
        level_schemes: list[Literal["pairwise", "mosaic"]]
        uncertainty: bool
        executor: Literal["serial", "threads", "dask"]
        workers: int
        dask_address: str | None
        outputs: OutputsConfig

    @model_validator(mode="before")
    @classmethod
    def _former_keys(cls, data: Any) -> Any:
        # keys of earlier specs, read under their present names
        if isinstance(data, dict) and ("scale" in data or "refine_locator" in data):
            data = dict(data)
            move_scale(data, DEFAULT_PLUGINS["compositor"])
            move_refine_locator(data)
        return data

    @property
    def scale(self) -> float:
        """The compositor's super-resolution scale (canvas pixels per frame pixel)."""
        return self.compositor.scale

    @field_validator(*STAGES, mode="before", check_fields=False)
    @classmethod
    def _plugin_shorthand(cls, value: Any) -> Any:
        return {"plugin": value} if isinstance(value, str) else value

    @model_validator(mode="after")
    def _level_one_is_pairwise(self) -> Any:
        if self.level_schemes[0] != "pairwise":
            raise ValueError("level_schemes: level 1 must be pairwise (the mosaic scheme refines an existing "
                             "estimate)")
        return self


PipelineSpec = _SpecBase
"""The type of a validated spec: every model :func:`spec_model` builds subclasses it."""


def _group_size(value: Any) -> Any:
    """Accept ``"auto"`` or an integer >= 2 as a group size, with one message for anything else."""
    if value == "auto" or (isinstance(value, int) and not isinstance(value, bool) and value >= 2):
        return value
    raise ValueError("expected an integer >= 2 (binary frames per group) or auto")


def _on_off(value: Any) -> Any:
    """Read YAML's ``off``/``false`` (a bool to a YAML 1.1 parser) as ``"off"``, ``on``/``true`` as ``"auto"``."""
    return ("auto" if value else "off") if isinstance(value, bool) else value


def _tagged(classes: list[type]) -> Any:
    return Annotated[Union[tuple(classes)], Field(discriminator="plugin")]  # noqa: UP007


def spec_model(host: PluginHost) -> type[PipelineSpec]:
    """Build the ``PipelineSpec`` model for the plugins installed in ``host``.

    Raises:
        PluginError: if a stage kind has no plugin at all.
    """
    slots: dict[str, Any] = {}
    for stage in STAGES:
        classes = list(host.registry(stage).values())
        if stage == "pose_estimator":  # optional: a spec with it runs `photonpano pose`
            tagged = _tagged(classes) if classes else None
            slots[stage] = (Annotated[Union[tagged, None], Field(  # noqa: UP007
                description="Experimental: estimate 6-DoF camera poses instead of a panorama.")], None)
            continue
        if not classes:
            raise PluginError(f"no {stage} plugins are installed (is photonpano installed?)")
        if stage == "source":
            slots[stage] = (_tagged(classes), ...)
        else:
            default_cls = host.registry(stage).get(DEFAULT_PLUGINS[stage], classes[0])
            slots[stage] = (_tagged(classes), Field(default_factory=default_cls))
    mosaic = _mosaic_model(host)
    slots["mosaic"] = (mosaic, Field(default_factory=mosaic, description="Locator and template of the levels "
                                     "whose scheme is mosaic (see [mosaic](#mosaic))."))
    # the settings as a mapping: mypy reads Annotated[...] values in call arguments as type forms
    fields: dict[str, Any] = {
        "version": (Literal[1], 1),
        **slots,
        "levels": (Annotated[int, Field(ge=1, le=8, description="Number of levels (iterations of "
                                     "re-sample, merge, locate, interpolate).")], 3),
        "group_size": (Annotated[Union[Literal["auto"], Annotated[int, Field(ge=2)]],  # noqa: UP007
                              BeforeValidator(_group_size), Field(
            description="Binary frames per group m (virtual exposure length, in frames); auto: "
            "chosen from the capture's photon rate and apparent speed (photonpano.budget).")], "auto"),
        "pair_offsets": (Annotated[list[Annotated[int, Field(ge=1)]], Field(
            min_length=1, description="Register merged frames g and g+k for each k; [1] is the "
            "paper's chain, more offsets are solved jointly against chaining drift.")], [1, 2, 4, 8, 16, 32, 64]),
        "camera_model": (Literal["auto", "homography"], Field("auto", description=
            "How a pairwise level's pose graph models the camera. auto: where the level's camera turns out of the "
            "image plane (its registrations carry a steady keystone, as on a tripod pan), one focal length and a "
            "rotation per keyframe (a camera turning about its centre, H = K R K^-1, as OpenCV's stitching "
            "module's ray bundle adjustment), kept where it agrees with the pairs within 1.5x of the free "
            "solution (photonpano.turning_camera; run.json `registration_check.turning_camera`); tripod pans: "
            "the outdoor camera 0.650 -> 0.327 px, Hubble 1.47 -> 0.43, coffee 0.371 -> 0.222. homography: every "
            "keyframe its own homography (the paper's).")),
        "registration_binning": (Annotated[Union[Literal["auto"], Annotated[int, Field(ge=1, le=8)]],  # noqa: UP007
                                        Field(description=
            "Level 1 (and any pairwise level) estimates motion on merged frames binned k x k (the photons of k x "
            "k sensor pixels summed): 2 gives the locators the half-resolution images they register anyway for a "
            "quarter of the merging work; 1 merges at full resolution (e.g. with `locator.image_scale: 0.5` for "
            "SIFT's former default). auto: 2 where the binned frames keep at least 100 pixels on their short "
            "side, else 1 (photonpano.budget.binnings.auto_binning). The mosaic levels have their own, "
            "`mosaic.registration_binning`. The panorama is always composited from the full-resolution "
            "photons.")], "auto"),
        "hot_pixels": (Annotated[Literal["auto", "off"], BeforeValidator(_on_off)], Field("auto", description=
            "Hot and dead pixels (a detection probability fixed on the sensor, not on the scene): auto finds them "
            "in the capture's own photon counts (8 000 frames read in 8 stretches: isolated pixels whose rate "
            "stands more than 6 standard deviations off their 3x3 neighbourhood's median, on one side, while the "
            "scene moves; on a colour-filtered sensor, behind every filter too) and inpaints their counts from "
            "their 4-neighbours for every stage, the colour planes included "
            "(photonpano.hot_pixels; run.json `hot_pixels`, hot_pixels.npy: a SwissSPAD source's `inpaint_mask` "
            "for the next captures of that sensor, where it has no `transforms`). In a capture whose scene did "
            "not move none is flagged (a defect and a sharp detail look alike there). off (or false): every pixel "
            "is used as read.")),
        "panorama_subbatch_px": (Annotated[float, Field(gt=0, le=2, description="Frames whose canvas "
                              "warps differ by less than this (canvas pixels) are warped together.")], 0.5),
        "level_schemes": (Annotated[list[Literal["pairwise", "mosaic"]], Field(
            min_length=1, description="Scheme of each level, the last repeated for the levels after: pairwise "
            "(the paper's: pairs of merged frames and a pose graph; level 1 is always pairwise) or mosaic (each "
            "merged frame against the panorama of the current estimate: no drift, one registration per "
            "group).")], ["pairwise", "mosaic"]),
        "uncertainty": (bool, Field(True, description="Predict every frame's trajectory error (uncertainty.npy, "
                     "run.json `uncertainty`, and `status`) from registrations held out of the fit: the last level "
                     "also registers consecutive merged frames against each other, and chains of merged frames "
                     "far apart (photonpano.uncertainty, photonpano.long_pairs).")),
        "executor": (Literal["serial", "threads", "dask"], Field("threads", description="Where independent work "
                  "(groups, chunks) runs: the calling thread, a pool of threads, or a Dask cluster (a local one "
                  "of `workers` processes, or the scheduler at `dask_address`; see docs/scaling.md).")),
        "workers": (Annotated[int, Field(ge=0, description="Threads of the executor, or worker processes of a local "
                                      "Dask cluster (0 = one per CPU core).")], 0),
        "dask_address": (Annotated[str | None, Field(
            pattern=r"^(tcp|tls|inproc|ucx|ws|wss)://\S+$", description="executor dask: address of a running "
            "Dask scheduler, e.g. tcp://10.0.0.5:8786; null starts a local cluster of `workers` processes.")], None),
        "outputs": (OutputsConfig, Field(default_factory=OutputsConfig)),
    }
    model = create_model("PipelineSpec", __base__=_SpecBase, **fields)
    model.__doc__ = "A photonpano pipeline: one plugin per stage and the method's settings."
    return model


def _mosaic_model(host: PluginHost) -> type[BaseModel]:
    """The model of the ``mosaic`` section (locator and template compositor of the mosaic scheme)."""
    locators, compositors = host.registry("locator"), host.registry("compositor")

    def locator(value: Any) -> Any:
        value = {"plugin": value} if isinstance(value, str) else value
        if isinstance(value, dict):
            key = value.get("plugin", MOSAIC_PLUGINS["locator"])
            value = {**getattr(locators.get(key), "template_defaults", {}), **value, "plugin": key}
        return value

    def compositor(value: Any) -> Any:
        value = {"plugin": value} if isinstance(value, str) else value
        return {"plugin": MOSAIC_PLUGINS["template"], **value} if isinstance(value, dict) else value

    # PluginHost registers under "locator" only subclasses of LocatorConfig (it checks each class's base)
    default_locator = cast("type[LocatorConfig]", locators[MOSAIC_PLUGINS["locator"]])
    fields: dict[str, Any] = {  # a mapping: mypy reads Annotated[...] values in call arguments as type forms
        "locator": (Annotated[_tagged(list(locators.values())), BeforeValidator(locator), Field(
            description="Locator registering each merged frame against the panorama view at its pose.")],
            Field(default_factory=lambda: default_locator(**default_locator.template_defaults))),
        "template": (Annotated[_tagged(list(compositors.values())), BeforeValidator(compositor), Field(
            description="Compositor of the panorama registered against, made afresh at each mosaic level "
            "from the photons with that level's starting estimate.")],
            Field(default_factory=compositors[MOSAIC_PLUGINS["template"]])),
        "subbatch_px": (Annotated[float, Field(gt=0, le=2, description="Sub-batch tolerance of that panorama, "
                                            "in canvas pixels.")], 0.5),
        "reject_movers": (Annotated[Union[Literal["auto"], Annotated[float, Field(gt=0)], None], Field(  # noqa: UP007
            description="Leave out of each registration the pixels of a merged frame that disagree with the "
            "panorama view by more than this many robust standard deviations (a moving object, or its ghost), "
            "and composite `template` robustly (a mover never enters it). auto (the default): 5, engaged only "
            "where the first mosaic level's robust template leaves out one region of at least 5 % of the "
            "canvas (a mover was found; run.json `movers`), else every pixel is used as with null. A number: always "
            "on (it also untrusts what the current estimate misregisters; Hubble field 0.0273 -> 0.0272 px; "
            "docs/real_scenes.md). null: every pixel is used.")], "auto"),
        "holdout": (Annotated[int, Field(ge=1, le=64, description="Runs of consecutive frames the template is "
            "cut into: each merged frame is registered against the panorama of the runs its frames do not fall in "
            "(a leave-one-out template: its own photons, and those of the neighbours that share its pose error, "
            "do not pull it toward the current estimate; photonpano.schemes.holdout.HoldoutTemplate). With the "
            "flux-canvas template, while movers are not rejected. 1 (the default): every photon. 4 suits a pan "
            "that ends on scenery only its last frames see (the bundled office: 0.124 -> 0.033 px); on most "
            "suite captures the unbiased registrations are noisier and the RMSE rises (docs/accuracy.md).")], 1),
        "correct_template_bias": (Annotated[bool, Field(description="Correct each registration for the error the "
            "template shares with it: the template is made with the estimate being corrected, so a registration "
            "against it sees a group's error only relative to the mean error of the frames that see the same "
            "canvas, and errors a stretch of the capture shares are corrected slowly. The smooth error is fitted "
            "to all registrations through a linear model of that bias and each registration is corrected by its "
            "bias (photonpano.schemes.template_bias; run.json levels[k].template_bias). Evaluation suite, 48 "
            "captures: RMSE geometric mean -10 %, 14 better, 3 worse (the bundled office 0.124 -> 0.068 px); "
            "false: as before.")],
            True),
        "correct_shape_drift": (Annotated[bool, Field(description="Take the shape error that grows slowly along "
            "the capture out of the last level's trajectory: that level also registers 8 chains of merged frames "
            "far apart (the uncertainty's shape term, photonpano.long_pairs), and what their mean error stands "
            "at 3 standard errors or more in a homography parameter is removed, in up to 5 steps "
            "(photonpano.long_pairs.correct_shape_drift; run.json levels[k].shape_drift_px). A 50-degree tripod "
            "pan (source.pan_model: rotation), 20 000 frames: the city 0.314 -> 0.075 px, the mountains 0.225 -> "
            "0.064, the gravel 0.158 -> 0.043, the astronaut 0.494 -> 0.108 (docs/accuracy.md). The chains are "
            "registered with `uncertainty: false` too. false: as before.")], True),
        "perspective_levels": (Annotated[Union[Annotated[int, Field(ge=1)], None], Field(  # noqa: UP007
            description="Mosaic levels that register the frames' perspective (the homography's p7, p8) against the "
            "panorama; the later ones register affine corrections (`locator` with `motion: affine`, where it has a "
            "`motion` that is `homography`). The perspective is the least determined part of a registration "
            "against the panorama, and each level adds its bias there: from the true trajectory, the sunset at "
            "flux 0.05 gains a keystone ramp of 0.04 then 0.08 px over levels 2 and 3, the Shepp-Logan phantom "
            "0.13 then 0.46. The first mosaic level still takes level 1's perspective error out, and the last "
            "level's held-out chains (`correct_shape_drift`) a slow drift of it. Evaluation suite, 48 captures: "
            "RMSE geometric mean -3 %, 18 better, 8 worse by 4-12 % (the clock under a 100 Hz lamp 0.128 -> "
            "0.141 px); the base captures at flux 0.05, four photon draws: the sunset 0.115 -> 0.081 px "
            "(docs/accuracy.md). null: every mosaic level registers the perspective (as before).")], 1),
        "template_bias_priors": (Literal["shared", "per-parameter"], Field("shared", description="The prior of "
            "that smooth error: one standard deviation for all 8 homography parameters (shared), or one per "
            "parameter (per-parameter: automatic relevance determination, photonpano.schemes.template_bias). "
            "per-parameter takes out an error concentrated in one parameter, as a turning camera's keystone: a "
            "keystone ramp injected into the truth is corrected 0.82 in one level instead of 0.42, a 50-degree "
            "tripod pan 0.49 -> 0.41 px (astronaut), 0.31 -> 0.26 px (city); evaluation suite RMSE geometric "
            "mean -4 % (the dark outdoor scene 0.30 -> 0.13 px, the clock 0.23 -> 0.14, up to +21 % on others). "
            "Not the default: the uncertainty's level-change term, calibrated on the shared prior's slower "
            "convergence, then calls the dark scene's first 62 frames over 1 px (0.37 px).")),
        "registration_binning": (Annotated[Union[Literal["auto"], Annotated[int, Field(ge=1, le=8)]], Field(  # noqa: UP007
            description="Binning k of the merged frames and templates of the mosaic levels (see the top-level "
            "`registration_binning`). auto: the top-level value where that is set in the spec; else full "
            "resolution (1) where the capture holds at most 6e9 pixel-frames (frames x height x width: about "
            "47 600 frames of 254x496) and a level-1 group gathers at least 10 photons per pixel, binned as "
            "level 1 otherwise (photonpano.budget.binnings.mosaic_binning). On the evaluation suite full "
            "resolution cut the trajectory RMSE of 32 of those 35 captures (city 0.060 -> 0.037 px) and raised "
            "none, for about 1.35x the CPU time. A capture binned for its length whose held-out registrations "
            "then predict frames above 1 px runs the mosaic levels again at full resolution from level 1 (100 000 "
            "frames of the suite's clock: 0.295 -> 0.131 px in 48 s instead of 23; docs/performance.md); where "
            "level 1's check registered 90 % or more of its pairs directly (its features failed: a scene of "
            "little texture) they run at full resolution from level 2 at once (the clock in 38 s, the same "
            "trajectory; photonpano.budget.binnings.little_texture).")], "auto"),
    }
    model = create_model("MosaicSpec", __config__=ConfigDict(extra="forbid", frozen=True), **fields)
    model.__doc__ = ("The mosaic level scheme registers each merged frame against the panorama of the current "
                     "estimate (frame-to-mosaic alignment): `locator` registers, `template` composites that "
                     "panorama. A locator here starts from its `template_defaults` (opencv-ecc: one pyramid level, "
                     "at most 10 iterations, stopping when the correlation gains less than 1e-4, on the merged "
                     "frames of `registration_binning`). The former `refine_locator: X` is read as "
                     "`mosaic: {locator: X}`, and `refine_locator: null` as `level_schemes: [pairwise]`.")
    return model


def level_schemes(spec: PipelineSpec) -> list[str]:
    """The scheme of each of the spec's levels (``level_schemes``, its last entry repeated)."""
    names = list(spec.level_schemes)
    return [names[min(i, len(names) - 1)] for i in range(spec.levels)]


def plugin_configs(spec: PipelineSpec) -> dict[str, Any]:
    """The plugin configs a spec uses: ``{"locator": ..., "mosaic.locator": ..., ...}``.

    Every stage slot that is set, and the mosaic scheme's locator and template when a
    level uses that scheme.
    """
    configs = {stage: getattr(spec, stage) for stage in STAGES if getattr(spec, stage, None) is not None}
    if "mosaic" in level_schemes(spec):
        configs.update({"mosaic.locator": spec.mosaic.locator, "mosaic.template": spec.mosaic.template})
    return configs
