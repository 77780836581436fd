"""The choices a reconstruction is made of, named once, and the one function that turns them into every stage's
settings.

``Quality``, ``Backend``, ``Device`` and ``Precision`` are the values of ``--quality``, ``--backend``,
``--device`` and ``--precision``; :func:`check_choice` refuses anything else with the option's own message (no
model or backend module is imported to check a string). :func:`configure` applies a quality preset, a backend and
the user's :class:`Overrides` (``--size``, ``--conf-threshold``, ``--budget``, ``--refine``) once, and returns a
:class:`StageSettings`: the pipeline's stages 1–6, the refinement (7) and the compaction (8). It is the one place
that resolves settings: ``macsplat reconstruct``, ``eval``, ``bench`` and :func:`macsplat_cli.engine.reconstruct`
all reach it through :meth:`macsplat_cli.engine.EngineConfig.settings`, so one quality gives one scene everywhere.
Every per-quality and per-backend difference lives here; a new preset is a new name in :data:`Quality` and a
branch in each function below that dispatches on it (``assert_never`` marks the branches a type checker makes you
fill).

This module imports no torch at import time (``macsplat --help`` reads its names); the stage settings it builds
are imported inside :func:`configure`. Measured: benchmarks/history/reconstruct.md.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import sys
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal, NoReturn, get_args

from .errors import InputError

if sys.version_info >= (3, 11):
    from typing import assert_never
else:  # pragma: no cover - Python 3.10

    def assert_never(value: NoReturn) -> NoReturn:
        """A dispatch reached a value its type does not allow (``typing.assert_never`` of Python 3.11)."""
        raise AssertionError(f"Expected code to be unreachable, but got: {value!r}")


if TYPE_CHECKING:
    from .pipeline.compact import CompactConfig
    from .pipeline.neural import NeuralConfig
    from .pipeline.pose import PoseSearchConfig
    from .pipeline.refine_config import RefineConfig
    from .pipeline.run import ReconstructConfig

__all__ = [
    "BACKENDS",
    "DEVICES",
    "FAST_SIFT",
    "DEFAULT_MATCHER",
    "MATCHERS",
    "MULTIVIEW_BALANCED_STEPS",
    "MULTIVIEW_SHARP_SCALE",
    "MULTIVIEW_BEST_STEPS",
    "MULTIVIEW_SHARP_MIN_GAIN_DB",
    "NEURAL_TAU",
    "PRECISIONS",
    "Overrides",
    "QUALITIES",
    "Backend",
    "Device",
    "Matcher",
    "Precision",
    "Quality",
    "StageSettings",
    "assert_never",
    "check_choice",
    "check_choices",
    "check_quality",
    "compact_config",
    "configure",
    "fusion_policy",
    "coarse_refinement",
    "refine_for_agreement",
    "refine_scale",
    "refine_steps",
    "resolved_refine_steps",
    "working_size",
]

Quality = Literal["fast", "balanced", "best"]
"""``--quality``: how light the stages are and how much of the scene's redundancy the compaction removes."""
Backend = Literal["classical", "neural"]
"""``--backend``: no learned weights, or MASt3R point maps and descriptors."""
Matcher = Literal["auto", "sift", "aliked"]
"""``--matcher`` (classical backend): SIFT, then ALIKED + LightGlue where SIFT's pose is not supported (``auto``);
SIFT only; or ALIKED + LightGlue only (its weight files required)."""
Device = Literal["cpu", "cuda"]
"""``--device``: where the networks run."""
Precision = Literal["fp32", "bf16"]
"""``--precision``: the networks' arithmetic (bf16: autocast)."""

QUALITIES: tuple[Quality, ...] = get_args(Quality)
BACKENDS: tuple[Backend, ...] = get_args(Backend)
DEVICES: tuple[Device, ...] = get_args(Device)
MATCHERS: tuple[Matcher, ...] = get_args(Matcher)
DEFAULT_MATCHER: Matcher = "auto"
"""``--matcher`` when none is given: SIFT's tiers, and the learned tier only where their pose fails or is not
supported. Its poses pass the learned tier's own guard too (repeated textures, a stricter a contrario bar:
``pipeline/learned/guard.py``), chosen on the pose protocol's tuning split, with no wrong learned pose accepted on
a fresh held-out draw (benchmarks/history/learned.md)."""
PRECISIONS: tuple[Precision, ...] = get_args(Precision)

FAST_SIFT = (640, 8000)
"""``--quality fast``, classical backend: SIFT's detection size and most keypoints (the defaults: 768, 8000; fewer
keypoints cost pose accuracy at wide baselines)."""
MULTIVIEW_BALANCED_STEPS = 5
"""``--quality balanced`` on three photos or more: the joint refinement's steps (``--refine`` units: 8 one-photo
steps on 4 photos, 16 on 8, :data:`~.pipeline.multiview.joint.RENDERS_PER_STEP`; at :data:`MULTIVIEW_SHARP_SCALE`
where the photos agree at it, else at 1/2), after the co-visibility init and before a compaction without the adaptive
merge and the dedup (:func:`configure`). At 1/2, mid / side gain over the middle pair:
object 4 +0.90 / +1.12 → +2.09 / +2.12 dB, room 4 +1.89 / +1.91 → +2.47 / +2.43, object 8 −0.43 → +0.28 at mid, room
8 −1.08 → −0.02; the 4-photo run 1.14–1.18× its time. 10 steps were no better (merge on: object 4 mid 21.85 → 21.79
dB, room 4 20.38 → 20.37) for twice the refinement's ~3 CPU-s (benchmarks/history/multiview_joint.md)."""
MULTIVIEW_SHARP_SCALE = 1
"""``--quality best`` and ``balanced`` on three photos or more: the joint refinement renders the photos at full
resolution (its ``--refine-scale``; pairs at 1/2) where the photos agree at it (:data:`MULTIVIEW_SHARP_MIN_GAIN_DB`;
else 1/2, :func:`coarse_refinement`). The refined Gaussians are what is written: refined pooled 2 × 2, object 4
rendered its held-out views blurred (``best``, mid / side 23.49 / 22.38 dB; at full resolution, 10 steps for the time
of 40: 25.28 / 23.20; room 4 21.91 / 20.79 → 22.05 / 20.54). ``balanced`` at 1/2 left 8 and 16 photos at or below
their middle pair at its views; sharp, mid gain object 8 +0.26 → +3.70 dB, room 8 −0.05 → +1.68, object 16 −0.81 →
+2.16, room 16 −0.96 → +0.75, object 4 +2.09 → +4.82, for 1.2–1.7× the run's time from 4 to 16 photos
(benchmarks/history/multiview_scaling.md)."""
MULTIVIEW_BEST_STEPS = 6
"""``--quality best`` on three photos or more: the joint refinement's steps (``--refine`` units: 10 one-photo steps
on 4 photos, 20 on 8, at :data:`MULTIVIEW_SHARP_SCALE`; a full-resolution step costs ~4 pooled ones, so the
refinement's time is that of ``best``'s 25 at 1/2: object 4 8.9 → 10.0 CPU-s, object 8 28.9 → 23.7)."""
MULTIVIEW_SHARP_MIN_GAIN_DB = 0.0
"""``best`` and ``balanced`` on three photos or more refine at :data:`MULTIVIEW_SHARP_SCALE` only where the other
photos' Gaussians predict the registered photos better sharp than pooled 2 × 2, by more than this (mean over the
photos, dB: :func:`~.pipeline.refine_stage.sharp_gain_db`); else as they did at 1/2 (:func:`coarse_refinement`).
Measured: object 4 +0.59, object 8 +1.06, room 8 +0.38 dB (full resolution gains up to 2.1 dB over 1/2 at held-out
views), room 4 −0.28 (mid +0.14, side −0.25), the development sets −0.15 (NYU 3) to −0.31 (CO3D 3), where full
resolution lost 0.07–0.56 dB (benchmarks/history/multiview_joint.md); with the measure's probes
(:data:`~.pipeline.refine_stage.PROBE_PHOTOS`) object 8 +0.92, room 8 +0.32, 16 photos +1.31 / +0.59, CO3D's 20
frames at 8 / 16 / 20 −0.17 / −0.09 / −0.03 (multiview_scaling.md)."""
NEURAL_TAU = 1.0
"""τ of the neural backend's matching on ``c0·c1`` of the descriptor confidences ``exp(x)`` (MASt3R's visloc keeps
pixels whose confidence exceeds 1.001)."""


def check_choice(option: str, value: str, choices: tuple[str, ...], *, sep: str = " or ") -> None:
    """Raise :class:`~macsplat_cli.errors.InputError` (``"--option 'value': use a or b"``) for a value not in
    ``choices``."""
    if value not in choices:
        raise InputError(f"{option} {value!r}: use {sep.join(choices)}")


def check_quality(quality: str) -> None:
    """:func:`check_choice` for ``--quality`` (its names are listed with commas)."""
    check_choice("--quality", quality, QUALITIES, sep=", ")


def working_size(quality: Quality) -> int:
    """The working images' long side when ``--size`` is not given."""
    if quality == "fast":
        return 384
    if quality == "balanced" or quality == "best":
        return 512  # MASt3R's training size
    assert_never(quality)


def fusion_policy(quality: Quality) -> Literal["always", "auto"]:
    """When the neural backend runs DINOv3 and the semantic fusion (:attr:`~.pipeline.neural.NeuralConfig.fusion`)."""
    if quality == "fast":
        return "auto"  # only when the backbone's own descriptors verify too few matches
    if quality == "balanced" or quality == "best":
        return "always"
    assert_never(quality)


def compact_config(quality: Quality, *, budget: int | None = None) -> CompactConfig:
    """The compaction's settings of a preset: ``"fast"`` (most reduction), ``"balanced"`` (the defaults of
    :class:`~.pipeline.compact.CompactConfig`) or ``"best"`` (only provably invisible Gaussians and exactly-zero SH
    bands are removed), at most ``budget`` Gaussians.

    Raises:
        InputError: an unknown quality.
    """
    from .pipeline.compact import CompactConfig

    check_quality(quality)
    if quality == "balanced":
        return CompactConfig(budget=budget)
    if quality == "fast":
        return CompactConfig(
            name="fast",
            max_block=16,
            color_tol=0.08,
            plane_tol=0.5,
            edge_depth_tol=0.2,
            prune_occluded=False,
            subpixel_px=0.0,
            budget=budget,
        )  # fmt: skip  (the z-buffer and footprint tests cost more time than they save Gaussians)
    if quality == "best":
        return CompactConfig(
            name="best", prune_floaters=False, dedup=False, prune_occluded=False, subpixel_px=0.0,
            adaptive=False, sh="zero", budget=budget,
        )  # fmt: skip
    assert_never(quality)


@dataclass
class StageSettings:
    """Every stage's settings of one reconstruction, as :func:`configure` made them.

    Attributes:
        pipeline: stages 1–6 (working size, descriptors, τ, pose, depth, Gaussians); what the report's ``config``
            section records.
        refine: stage 7 (``steps`` 0: it does not run).
        compact: stage 8.
        neural: the neural stages' settings (``--backend neural``), else None.
    """

    pipeline: ReconstructConfig
    refine: RefineConfig
    compact: CompactConfig
    neural: NeuralConfig | None = None


@dataclass(frozen=True)
class Overrides:
    """The user's overrides of a quality preset, each None where the preset (or the backend) decides.

    Attributes:
        size: ``--size``, the working images' long side (None: :func:`working_size`).
        conf_threshold: ``--conf-threshold`` τ of the filtered matching (None: 0.04 classically,
            :data:`NEURAL_TAU` for the neural backend).
        budget: ``--budget``, at most this many Gaussians in the scene, the far layer included (None: no limit).
        refine: ``--refine``, the refinement's steps (0: off; None: :func:`refine_steps` of the quality).
        refine_scale: ``--refine-scale``, the refinement's resolution 1/N (1 to 4; None: :func:`refine_scale`).
    """

    size: int | None = None
    conf_threshold: float | None = None
    budget: int | None = None
    refine: int | None = None
    refine_scale: int | None = None

    def check(self) -> None:
        """Raise :class:`~macsplat_cli.errors.InputError` for a value no preset could take the place of."""
        tau = self.conf_threshold
        if tau is not None and not (math.isfinite(tau) and tau >= 0):
            raise InputError(f"--conf-threshold {tau}: give a finite number ≥ 0")
        for option, value, what in (("--budget", self.budget, "a positive number of Gaussians"),
                                    ("--size", self.size, "a positive number of pixels"),
                                    ("--refine", self.refine, "a number of steps, auto or off")):  # fmt: skip
            low = 0 if option == "--refine" else 1
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < low):
                raise InputError(f"{option} {value!r}: give {what}")
        scale = self.refine_scale
        if scale is not None and (isinstance(scale, bool) or not isinstance(scale, int) or not 1 <= scale <= 4):
            raise InputError(f"--refine-scale {scale!r}: use 1 to 4")


def check_choices(quality: Quality, backend: Backend, matcher: Matcher, overrides: Overrides) -> None:
    """The user's choices, checked without importing any stage (the checks of :func:`configure`, which
    :meth:`~macsplat_cli.engine.EngineConfig.validate` also makes before any work).

    Raises:
        InputError: an unknown quality, backend or matcher; a learned matcher with the neural backend; an override
            out of range (:meth:`Overrides.check`).
    """
    check_quality(quality)
    check_choice("--backend", backend, BACKENDS)
    check_choice("--matcher", matcher, MATCHERS, sep=", ")
    if backend == "neural" and matcher == "aliked":
        raise InputError("--matcher aliked applies to --backend classical (the neural backend matches its own)")
    overrides.check()


def resolved_size(quality: Quality, overrides: Overrides) -> int:
    """The working images' long side: ``--size`` where given, else the quality's (:func:`working_size`)."""
    return overrides.size if overrides.size is not None else working_size(quality)


def resolved_refine_steps(quality: Quality, overrides: Overrides, photos: int = 2) -> int:
    """The refinement's steps: ``--refine`` where given, else the quality's for ``photos`` (:func:`refine_steps`)."""
    return overrides.refine if overrides.refine is not None else refine_steps(quality, photos)


def refine_scale(quality: Quality, photos: int = 2) -> int:
    """The refinement's resolution 1/N when ``--refine-scale`` is not given: :data:`MULTIVIEW_SHARP_SCALE` for
    ``best`` and ``balanced`` on three photos or more (the photos may decline it: :func:`coarse_refinement`), else
    :class:`~.pipeline.refine_config.RefineConfig`'s (1/2)."""
    from .pipeline.refine_config import RefineConfig

    return MULTIVIEW_SHARP_SCALE if quality in ("best", "balanced") and photos >= 3 else RefineConfig.scale


def coarse_refinement(quality: Quality, overrides: Overrides, photos: int = 2) -> tuple[int, int] | None:
    """The refinement's ``(scale, steps)`` where the photos do not agree at the preset's full resolution
    (:attr:`~.pipeline.refine_config.RefineConfig.coarse`): on three photos or more without ``--refine-scale``,
    1/2 and ``--refine`` or the preset's steps there (``best``: :data:`~.pipeline.refine_config.AUTO_STEPS`, its
    refinement before it refined at full resolution; ``balanced``: :data:`MULTIVIEW_BALANCED_STEPS`, as before);
    None where the scale is not the photos' to choose."""
    from .pipeline.refine_config import AUTO_STEPS, RefineConfig

    if overrides.refine_scale is not None or refine_scale(quality, photos) == RefineConfig.scale:
        return None
    if overrides.refine is not None:
        return RefineConfig.scale, overrides.refine
    return RefineConfig.scale, AUTO_STEPS if quality == "best" else MULTIVIEW_BALANCED_STEPS


def refine_for_agreement(config: RefineConfig, sharp_gain_db: float) -> RefineConfig:
    """The refinement ``config`` once the photos have been measured: its ``coarse`` scale and steps where the other
    photos' Gaussians predict a photo no better sharp than pooled (``sharp_gain_db`` not above
    :data:`MULTIVIEW_SHARP_MIN_GAIN_DB`, or NaN: no photo to measure), else ``config`` as it is (``coarse`` None:
    nothing to choose)."""
    if config.coarse is None or sharp_gain_db > MULTIVIEW_SHARP_MIN_GAIN_DB:
        return config
    scale, steps = config.coarse
    return dataclasses.replace(config, scale=scale, steps=steps, coarse=None)


def _balanced_set(quality: Quality, photos: int) -> bool:
    """``balanced`` on three photos or more: the co-visibility init, :data:`MULTIVIEW_BALANCED_STEPS` joint steps and
    a compaction without the merge and the dedup (:func:`configure`)."""
    return quality == "balanced" and photos >= 3


def refine_steps(quality: Quality, photos: int = 2) -> int:
    """The refinement's steps when ``--refine`` is not given: ``best`` refines for
    :data:`~.pipeline.refine.AUTO_STEPS` steps (about 6–8 s a 512-px pair on two cores for +0.1 to +1.1 dB on
    held-out views of the development pairs, ``benchmarks/history/refine.md``), on three photos or more for
    :data:`MULTIVIEW_BEST_STEPS` at full resolution (the refine stage takes :func:`coarse_refinement`'s where the
    photos do not agree at it); ``balanced`` on three photos or more for :data:`MULTIVIEW_BALANCED_STEPS` (the
    joint refinement, at full resolution where the photos agree); ``fast``, and ``balanced`` on two photos, do not
    (it would more than double their time)."""
    from .pipeline.refine_config import AUTO_STEPS

    check_quality(quality)
    if quality == "best":
        return MULTIVIEW_BEST_STEPS if photos >= 3 else AUTO_STEPS
    return MULTIVIEW_BALANCED_STEPS if _balanced_set(quality, photos) else 0


def configure(
    quality: Quality,
    backend: Backend,
    overrides: Overrides | None = None,
    *,
    pipeline: ReconstructConfig | None = None,
    refine: RefineConfig | None = None,
    precision: Precision = "fp32",
    matcher: Matcher = DEFAULT_MATCHER,
    photos: int = 2,
) -> StageSettings:
    """Every stage's settings from a preset, a backend and the user's overrides (the inputs are not modified).

    Args:
        quality: the preset: the working size (:func:`working_size`), the classical stages' speed (``"fast"``: SIFT
            at :data:`FAST_SIFT`, no slanted-plane PatchMatch), the neural fusion policy (:func:`fusion_policy`),
            the refinement's steps (:func:`refine_steps`) and the compaction (:func:`compact_config`).
        backend: ``"neural"`` turns off the SIFT fallback tiers and the epipolar-guided re-matching (the pose does
            not come from the matches) and matches on the learned confidence as it is (``ratio_confidence=False``).
        overrides: ``--size``, ``--conf-threshold``, ``--budget`` and ``--refine`` (default: none).
        pipeline: the stage settings to start from (default: :class:`~.pipeline.run.ReconstructConfig`): the
            inputs (intrinsics, poses, far layer) and any research setting; its ``views.size`` and
            ``matching.conf_threshold`` are replaced (the working size and τ are resolved here).
        refine: how the refinement runs (scale, MAC, LPIPS; default :class:`~.pipeline.refine.RefineConfig`); its
            ``steps`` are replaced by ``overrides.refine`` or the preset's.
        precision: the neural backend's arithmetic.
        matcher: ``--matcher`` (:func:`learned_search`); the neural backend has its own matches (``auto``: none).
        photos: how many photos are reconstructed: ``balanced`` on three or more refines them jointly
            (:func:`refine_steps`) after the co-visibility init, and its compaction keeps the refined Gaussians
            unmerged and leaves the dedup to that init (the adaptive merge took 0.3–1.5 dB of the refined 4- and
            8-photo scenes, the dedup 0.2–0.6 more: object 8 mid 21.85 → 21.26 → 19.81 dB,
            benchmarks/history/multiview_joint.md).

    Raises:
        InputError: an unknown quality, backend or matcher; a learned matcher with the neural backend; an override
            out of range (:meth:`Overrides.check`).
    """
    from .pipeline.matching import MatchConfig
    from .pipeline.refine_config import RefineConfig
    from .pipeline.run import ReconstructConfig

    o = overrides or Overrides()
    check_choices(quality, backend, matcher, o)
    c = copy.deepcopy(pipeline) if pipeline is not None else ReconstructConfig()
    c.views = dataclasses.replace(c.views, size=resolved_size(quality, o))
    neural = None
    if backend == "classical":
        tau = MatchConfig.conf_threshold if o.conf_threshold is None else o.conf_threshold
        c.matching = dataclasses.replace(c.matching, conf_threshold=tau)
        if quality == "fast":  # SIFT on a smaller image, no slanted-plane PatchMatch in the depth
            d = c.descriptors
            c.descriptors = dataclasses.replace(
                d, detect_size=min(d.detect_size, FAST_SIFT[0]), max_keypoints=min(d.max_keypoints, FAST_SIFT[1])
            )
            c.depth = dataclasses.replace(c.depth, slanted_iters=0)
        c.search = learned_search(c.search, matcher)
        if quality == "best" or _balanced_set(quality, photos):  # one Gaussian per surface point before
            c.multiview = dataclasses.replace(c.multiview, covisibility=True)  # the joint refinement
    elif backend == "neural":
        from .pipeline.neural import NeuralConfig

        c.search = dataclasses.replace(c.search, fallback=False, guided_band_px=None)
        tau = NEURAL_TAU if o.conf_threshold is None else o.conf_threshold
        c.matching = MatchConfig(conf_threshold=tau, ratio_confidence=False, max_block_elems=c.matching.max_block_elems)
        neural = NeuralConfig(precision=precision, fusion=fusion_policy(quality))
    else:
        assert_never(backend)
    steps = resolved_refine_steps(quality, o, photos)
    scale = o.refine_scale if o.refine_scale is not None else refine_scale(quality, photos)
    r = dataclasses.replace(copy.deepcopy(refine) if refine is not None else RefineConfig(), steps=steps, scale=scale,
                            coarse=coarse_refinement(quality, o, photos) if steps > 0 else None)  # fmt: skip
    compact = compact_config(quality, budget=o.budget)
    if _balanced_set(quality, photos) and steps > 0:  # refined jointly: kept unmerged, the covis init deduped
        compact = dataclasses.replace(compact, adaptive=False, dedup=False)
    return StageSettings(c, r, compact, neural)


def learned_search(search: PoseSearchConfig, matcher: Matcher) -> PoseSearchConfig:
    """The pose search's tiers for ``--matcher`` (classical backend): ``sift`` the SIFT tiers only; ``auto`` the
    learned tier (ALIKED + LightGlue) after them, where their pose fails or is not supported; ``aliked`` the learned
    matcher as the one tier (no SIFT tier: its fallback and wide tiers match SIFT descriptors)."""
    from .pipeline.learned import LearnedConfig

    if matcher == "sift":
        return dataclasses.replace(search, learned=None, learned_primary=False)
    if matcher == "auto":
        return dataclasses.replace(search, learned=search.learned or LearnedConfig(), learned_primary=False)
    if matcher == "aliked":
        return dataclasses.replace(search, learned=search.learned or LearnedConfig(), learned_primary=True,
                                   fallback=False, wide=False)  # fmt: skip
    assert_never(matcher)
