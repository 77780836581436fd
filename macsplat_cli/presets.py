"""The choices a reconstruction is made of, named once, and the one function that turns them into every stage's
settings.

``Quality``, ``Backend``, ``Device`` and ``Precision`` are the values of ``--quality``, ``--backend``,
``--device`` and ``--precision``; :func:`check_choice` refuses anything else with the option's own message (no
model or backend module is imported to check a string). :func:`configure` applies a quality preset, a backend and
the user's overrides (``--size``, ``--conf-threshold``, ``--budget``, ``--precision``) once, and returns a
:class:`StageSettings`: the pipeline's stages 1–6, the refinement (7) and the compaction (8). Every per-quality and
per-backend difference lives here; a new preset is a new name in :data:`Quality` and a branch in each function
below that dispatches on it (``assert_never`` marks the branches a type checker makes you fill).

This module imports no torch at import time (``macsplat --help`` reads its names); the stage settings it builds
are imported inside :func:`configure`. Measured: benchmarks/history/reconstruct.md.
"""

from __future__ import annotations

import copy
import dataclasses
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
    from .pipeline.refine import RefineConfig
    from .pipeline.run import ReconstructConfig

__all__ = [
    "BACKENDS",
    "DEVICES",
    "FAST_SIFT",
    "MATCHERS",
    "NEURAL_TAU",
    "PRECISIONS",
    "QUALITIES",
    "Backend",
    "Device",
    "Matcher",
    "Precision",
    "Quality",
    "StageSettings",
    "assert_never",
    "check_choice",
    "check_quality",
    "compact_config",
    "configure",
    "fusion_policy",
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
PRECISIONS: tuple[Precision, ...] = get_args(Precision)

FAST_SIFT = (640, 8000)
"""``--quality fast``, classical backend: SIFT's detection size and most keypoints (the defaults: 768, 8000; fewer
keypoints cost pose accuracy at wide baselines)."""
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


def refine_steps(quality: Quality) -> int:
    """``reconstruct``'s refinement when ``--refine`` is not given: ``best`` refines for
    :data:`~.pipeline.refine.AUTO_STEPS` steps (about 6–8 s a 512-px pair on two cores for +0.1 to +1.1 dB on
    held-out views of the development pairs, ``benchmarks/history/refine.md``); ``fast`` and ``balanced`` do not
    (it would more than double their time)."""
    from .pipeline.refine import AUTO_STEPS

    check_quality(quality)
    return AUTO_STEPS if quality == "best" else 0


def configure(
    quality: Quality,
    backend: Backend,
    *,
    pipeline: ReconstructConfig | None = None,
    size: int | None = None,
    conf_threshold: float | None = None,
    budget: int | None = None,
    refine: RefineConfig | None = None,
    precision: Precision = "fp32",
    matcher: Matcher = "auto",
) -> StageSettings:
    """Every stage's settings from a preset, a backend and the user's overrides (the inputs are not modified).

    Args:
        quality: the preset: the working size (:func:`working_size`), the classical stages' speed (``"fast"``: SIFT
            at :data:`FAST_SIFT`, no slanted-plane PatchMatch), the neural fusion policy (:func:`fusion_policy`) and
            the compaction (:func:`compact_config`).
        backend: ``"neural"`` turns off the SIFT fallback tiers and the epipolar-guided re-matching (the pose does
            not come from the matches) and matches on the learned confidence as it is (``ratio_confidence=False``).
        pipeline: the caller's stage settings to start from (default: :class:`~.pipeline.run.ReconstructConfig`);
            its ``views.size`` is replaced by the working size.
        size: ``--size``, the working long side (None: the preset's).
        conf_threshold: ``--conf-threshold`` τ (None: the backend's, ``pipeline.matching``'s classically,
            :data:`NEURAL_TAU` for the neural backend).
        budget: ``--budget``, at most this many Gaussians (None: no limit).
        refine: the refinement (default: off).
        precision: the neural backend's arithmetic.
        matcher: ``--matcher`` (:func:`learned_search`); the neural backend has its own matches (``auto``: none).

    Raises:
        InputError: an unknown quality, backend or matcher; a learned matcher with the neural backend.
    """
    from .pipeline.refine import RefineConfig
    from .pipeline.run import ReconstructConfig

    check_quality(quality)
    check_choice("--backend", backend, BACKENDS)
    check_choice("--matcher", matcher, MATCHERS, sep=", ")
    c = copy.deepcopy(pipeline) if pipeline is not None else ReconstructConfig()
    c.views = dataclasses.replace(c.views, size=size if size is not None else working_size(quality))
    neural = None
    if backend == "classical":
        if conf_threshold is not None:
            c.matching = dataclasses.replace(c.matching, conf_threshold=conf_threshold)
        if quality == "fast":  # SIFT on a smaller image, no slanted-plane PatchMatch in the depth
            d = c.descriptors
            c.descriptors = dataclasses.replace(
                d, detect_size=min(d.detect_size, FAST_SIFT[0]), max_keypoints=min(d.max_keypoints, FAST_SIFT[1])
            )
            c.depth = dataclasses.replace(c.depth, slanted_iters=0)
        c.search = learned_search(c.search, matcher)
    elif backend == "neural":
        if matcher == "aliked":
            raise InputError("--matcher aliked applies to --backend classical (the neural backend matches its own)")
        from .pipeline.matching import MatchConfig
        from .pipeline.neural import NeuralConfig

        c.search = dataclasses.replace(c.search, fallback_descriptors=None, guided_band_px=None)
        tau = NEURAL_TAU if conf_threshold is None else conf_threshold
        c.matching = MatchConfig(conf_threshold=tau, ratio_confidence=False, max_block_elems=c.matching.max_block_elems)
        neural = NeuralConfig(precision=precision, fusion=fusion_policy(quality))
    else:
        assert_never(backend)
    refine = copy.deepcopy(refine) if refine is not None else RefineConfig()
    return StageSettings(c, refine, compact_config(quality, budget=budget), neural)


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
                                   fallback_descriptors=None, wide_descriptors=None)  # fmt: skip
    assert_never(matcher)
