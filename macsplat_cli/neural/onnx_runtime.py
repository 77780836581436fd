"""An exported predictor run by onnxruntime, in place of the torch :class:`~.predictor.PairPredictor`.

:class:`OnnxPairPredictor` has what the pipeline's neural stages use of a ``PairPredictor`` —
``predict(img0, img1)``, ``output_names``, ``desc_dim``, ``has_gaussian_head``, ``fusion_enabled``, the
report strings — so ``reconstruct``/``eval``/``bench --backend neural --weights predictor.onnx`` run the
same downstream stages. The file is checked before any work: its inputs and outputs must be a macsplat
predictor's and its metadata readable (:func:`read_predictor_info`).

Providers: the CPU, or CUDA (``device="cuda"``) when onnxruntime was built with it. ORT's worker
threads busy-wait after each run by default, which steals the cores from the torch stages that follow
in the same process; the pipeline turns that off (``spinning=False``).
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..errors import InputError, ShapeError
from .checkpoints import CheckpointNotFoundError
from .onnx_format import INPUT_NAMES, METADATA_KEY, OnnxPredictorError, OnnxPredictorInfo, expected_output_names
from .predictor import PairPrediction, prediction_from_outputs

__all__ = ["OnnxPairPredictor", "is_onnx_file", "ort_providers", "read_predictor_info"]

logger = logging.getLogger(__name__)


def is_onnx_file(path: Path | str | None) -> bool:
    """An ONNX predictor is recognised by its extension."""
    return path is not None and Path(path).suffix.lower() == ".onnx"


def _import_ort() -> Any:
    try:
        import onnxruntime as ort
    except ImportError:
        raise InputError(
            "running an .onnx predictor needs onnxruntime: pip install -c constraints.txt -e '.[onnx]'"
        ) from None
    return ort


def ort_providers(device: str) -> list[str]:
    """onnxruntime execution providers for ``device`` (``"cpu"`` or ``"cuda"``).

    Raises:
        InputError: CUDA asked for where onnxruntime has no CUDA provider.
    """
    ort = _import_ort()
    if device == "cuda":
        if "CUDAExecutionProvider" not in ort.get_available_providers():
            raise InputError(
                f"--device cuda: this onnxruntime ({ort.__version__}) has no CUDA provider "
                "(install onnxruntime-gpu), or use --device cpu"
            )
        return ["CUDAExecutionProvider", "CPUExecutionProvider"]
    if device != "cpu":
        raise InputError(f"--device {device!r}: use cpu or cuda")
    return ["CPUExecutionProvider"]


def _elem_type_name(t: int) -> str:
    import onnx

    return onnx.TensorProto.DataType.Name(t).lower()


def read_predictor_info(path: Path | str) -> OnnxPredictorInfo:
    """Check that ``path`` is a macsplat ONNX predictor and return its metadata (the weights are not read).

    Raises:
        CheckpointNotFoundError: no such file.
        OnnxPredictorError: not an ONNX model, inputs/outputs that are not a macsplat predictor's (the
            message names the mismatch), or missing/unreadable macsplat metadata.
    """
    import onnx

    p = Path(path)
    if not p.is_file():
        raise CheckpointNotFoundError(f"ONNX predictor {p} not found" + (" (it is a folder)" if p.is_dir() else ""))
    try:
        model = onnx.load(str(p), load_external_data=False)
    except Exception as e:  # noqa: BLE001 - protobuf raises several types on garbage
        raise OnnxPredictorError(f"{p} is not an ONNX model ({type(e).__name__}: {e})") from None
    graph = model.graph
    initializer_names = {t.name for t in graph.initializer}
    inputs = [i for i in graph.input if i.name not in initializer_names]
    names = tuple(i.name for i in inputs)
    if names != INPUT_NAMES:
        raise OnnxPredictorError(f"{p} is not a macsplat predictor: its inputs are {list(names)}, expected img0, img1")
    for i in inputs:
        tt = i.type.tensor_type
        dims = [d.dim_value if d.HasField("dim_value") else d.dim_param for d in tt.shape.dim]
        if tt.elem_type != onnx.TensorProto.FLOAT or len(dims) != 4 or dims[1] != 3:
            raise OnnxPredictorError(
                f"{p} is not a macsplat predictor: input {i.name} is {_elem_type_name(tt.elem_type)} {dims}, "
                "expected float [B, 3, H, W]"
            )
    outs = tuple(o.name for o in graph.output)
    props = {m.key: m.value for m in model.metadata_props}
    if METADATA_KEY not in props:
        raise OnnxPredictorError(
            f"{p} has no macsplat metadata ({METADATA_KEY}): export it with 'macsplat export-onnx'"
        )
    info = OnnxPredictorInfo.from_json(props[METADATA_KEY], str(p))
    want = expected_output_names(info.gaussian_head)
    if outs != want:
        missing = [n for n in want if n not in outs]
        extra = [n for n in outs if n not in want]
        parts = [f"missing {', '.join(missing)}"] if missing else []
        parts += [f"unexpected {', '.join(extra)}"] if extra else []
        what = "; ".join(parts) or f"in the order {list(outs)}"
        raise OnnxPredictorError(f"{p} is not a macsplat predictor: its outputs do not fit ({what})")
    return info


class OnnxPairPredictor:
    """A macsplat ONNX predictor in an onnxruntime session, with the interface the pipeline uses.

    Args:
        path: the ``.onnx`` file (``.onnx.data`` beside it for large models).
        device: ``"cpu"`` or ``"cuda"`` (the CUDA provider).
        threads: ORT intra-op threads (None: onnxruntime's default, one per core).
        spinning: let ORT's threads busy-wait between runs (fast when ORT runs alone; steals the cores
            from torch code in the same process).

    Raises:
        see :func:`read_predictor_info` and :func:`ort_providers`.
    """

    def __init__(
        self, path: Path | str, *, device: str = "cpu", threads: int | None = None, spinning: bool = False
    ) -> None:
        ort = _import_ort()
        self.path = Path(path)
        self.info = read_predictor_info(self.path)
        providers = ort_providers(device)
        so = ort.SessionOptions()
        so.log_severity_level = 3
        if threads is not None:
            so.intra_op_num_threads = int(threads)
        if not spinning:
            so.add_session_config_entry("session.intra_op.allow_spinning", "0")
        t0 = time.perf_counter()
        try:
            self.session = ort.InferenceSession(str(self.path), sess_options=so, providers=providers)
        except Exception as e:  # noqa: BLE001 - onnxruntime raises its own Fail/InvalidGraph types
            raise OnnxPredictorError(f"onnxruntime cannot load {self.path}: {' '.join(str(e).split())}") from None
        self.device = device
        self.providers = self.session.get_providers()
        self.output_names = tuple(o.name for o in self.session.get_outputs())
        sizes = "dynamic size" if self.info.dynamic else "{}x{} only".format(*self.info.size)
        logger.info(
            "ONNX predictor %s (%s, %s) loaded in %.1f s on %s",
            self.path.name, self.info.precision, sizes, time.perf_counter() - t0, self.providers[0],
        )  # fmt: skip

    # ------------------------------------------------------------------ what the pipeline reads
    @property
    def desc_dim(self) -> int:
        return int(self.info.desc_dim)

    @property
    def has_gaussian_head(self) -> bool:
        return bool(self.info.gaussian_head)

    @property
    def fusion_enabled(self) -> bool:
        return bool(self.info.fusion_enabled)

    @property
    def input_size(self) -> tuple[int, int] | None:
        """``(W, H)`` the file only accepts, or None for any multiple of 16."""
        return None if self.info.dynamic else self.info.size

    @property
    def square_input(self) -> int | None:
        """As :attr:`PairPredictor.square_input`, from the configuration in the metadata."""
        img_size = (self.info.config.get("backbone") or {}).get("img_size")
        return 224 if img_size is not None and tuple(img_size) == (224, 224) else None

    def network_name(self) -> str:
        return f"onnx {self.path.name} ({self.info.network}, {self.info.precision}, {self.providers[0]})"

    def fusion_name(self) -> str:
        return self.info.fusion

    def fusion_detail(self, size: tuple[int, int]) -> str:
        return self.info.fusion_detail(size)

    # ------------------------------------------------------------------ computation
    def _check(self, img0: torch.Tensor, img1: torch.Tensor) -> None:
        if img0.dim() != 4 or img0.shape[1] != 3:
            raise ShapeError("img0", tuple(img0.shape), "[B, 3, H, W]")
        if img1.shape != img0.shape:
            raise ShapeError("img1", tuple(img1.shape), f"the shape of img0 {list(img0.shape)}")
        h, w = int(img0.shape[2]), int(img0.shape[3])
        if self.info.dynamic:
            if h % 16 or w % 16 or h == 0 or w == 0:
                raise ShapeError("img0", tuple(img0.shape), "[B, 3, H, W] with H and W positive multiples of 16")
        elif (w, h) != tuple(self.info.size):
            raise InputError(
                f"{self.path.name} was exported for {self.info.size[0]}x{self.info.size[1]} inputs only, got {w}x{h}"
            )

    def __call__(self, img0: torch.Tensor, img1: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """:meth:`PairPredictor.forward` through onnxruntime: ``[B, 3, H, W]`` in [0, 1] → the output tuple (CPU)."""
        self._check(img0, img1)
        feeds = {
            name: np.ascontiguousarray(t.detach().to("cpu", torch.float32).numpy())
            for name, t in zip(INPUT_NAMES, (img0, img1))
        }
        outputs = self.session.run(None, feeds)
        return tuple(torch.from_numpy(np.asarray(o, dtype=np.float32)) for o in outputs)

    forward = __call__

    def predict(self, img0: torch.Tensor, img1: torch.Tensor) -> PairPrediction:
        """The outputs named, as :meth:`PairPredictor.predict`."""
        return prediction_from_outputs(self(img0, img1))

    def __repr__(self) -> str:
        return f"OnnxPairPredictor({os.fspath(self.path)!r}, providers={self.providers})"
