"""An exported predictor run by onnxruntime, in place of the torch :class:`~.predictor.PairPredictor`.

:class:`OnnxPairPredictor` has what the pipeline's neural stages use of a ``PairPredictor`` —
``predict(img0, img1)``, ``output_names``, ``desc_dim``, ``has_gaussian_head``, ``fusion_enabled``, the
report strings — so ``reconstruct``/``eval``/``bench --backend neural --weights predictor.onnx`` run the
same downstream stages. The file is checked before any work: its inputs and outputs must be a macsplat
predictor's and its metadata readable (:func:`read_predictor_info`).

Providers: the CPU, or CUDA (``device="cuda"``) when onnxruntime was built with it. ORT's worker
threads busy-wait after each run by default, which steals the cores from the torch stages that follow
in the same process; the pipeline turns that off (``spinning=False``).

A file is untrusted input. Before onnxruntime sees it: only the operators the exporter writes
(:data:`~.onnx_format.ALLOWED_OPS`: no control flow, no custom operators, no subgraphs), external weights
only from regular files inside the model's folder, metadata of the right types and ranges. A run happens
in a worker thread so that Ctrl-C and SIGTERM, which Python delivers to the main thread, stop it within
seconds (onnxruntime is told to terminate between two nodes); a run that fails (an allocation too large,
a shape the graph cannot take) is an :class:`~.onnx_format.OnnxPredictorError`, one line. onnxruntime's
own log is silenced (its errors reach the user through that one line).
"""

from __future__ import annotations

import logging
import os
import re
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import torch

from ..errors import InputError, ShapeError
from .checkpoints import CheckpointNotFoundError
from .onnx_format import (
    INPUT_NAMES,
    METADATA_KEY,
    OnnxPredictorError,
    OnnxPredictorInfo,
    check_graph,
    expected_output_names,
)
from .predictor import PairPrediction, prediction_from_outputs

__all__ = ["OnnxPairPredictor", "is_onnx_file", "ort_providers", "read_predictor_info"]

logger = logging.getLogger(__name__)
_T = TypeVar("_T")

ORT_LOG_SEVERITY = 4
"""onnxruntime's log level for its sessions and its default logger: fatal only (3, "error", still prints a
coloured line of its own before macsplat's one-line error)."""
TERMINATE_WAIT_S = 5.0
"""How long an interrupted run is waited for once onnxruntime is told to terminate (it stops between two
nodes; a single node runs to its end)."""


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
    ort.set_default_logger_severity(ORT_LOG_SEVERITY)
    return ort


def _ort_message(e: BaseException) -> str:
    """onnxruntime's error as one short line: without its ``[ONNXRuntimeError] : 1 : FAIL :`` prefix and the
    source file and C++ signature it quotes."""
    if isinstance(e, MemoryError):
        return f"out of memory ({e})" if str(e) else "out of memory"
    text = " ".join(str(e).split())
    text = re.sub(r"^\[ONNXRuntimeError\] : \d+ : \w+ : ", "", text)
    text = re.sub(r"\S+\.(?:cc|cpp|h):\d+ (?:[^()]*\([^()]*\) )?", "", text) or type(e).__name__
    return text if len(text) <= 300 else text[:297] + "..."


def _is_ort_error(e: BaseException) -> bool:
    """onnxruntime's own exception types (Fail, RuntimeException, InvalidArgument, ...) or an allocation failure."""
    return isinstance(e, MemoryError) or type(e).__module__.startswith("onnxruntime")


def _in_worker(name: str, fn: Callable[[], _T], on_interrupt: Callable[[], None] | None = None) -> _T:
    """``fn()`` in a daemon thread while this thread waits for it.

    onnxruntime's calls hold the thread that makes them (a session's constant folding and a run can take
    as long as a file wants), and Python runs signal handlers in the main thread only between bytecodes:
    waiting here instead, Ctrl-C or SIGTERM (the CLI's handler) raise at once. Then ``on_interrupt`` (a
    run's ``RunOptions.terminate``) is called, the worker is given :data:`TERMINATE_WAIT_S` to stop, and
    the interrupt goes on; a worker that does not stop is a daemon and does not hold the process's exit.
    """
    box: dict[str, Any] = {}

    def work() -> None:
        try:
            box["value"] = fn()
        except BaseException as e:  # noqa: BLE001 - handed to the waiting thread
            box["error"] = e

    worker = threading.Thread(target=work, name=name, daemon=True)
    worker.start()
    try:
        while worker.is_alive():
            worker.join(0.1)
    except BaseException:
        if on_interrupt is not None:
            on_interrupt()
            worker.join(TERMINATE_WAIT_S)
        raise
    if "error" in box:
        raise box["error"]
    return box["value"]


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
            message names the mismatch), missing/unreadable macsplat metadata or a field of it out of range,
            operators or subgraphs the exporter never writes (:func:`~.onnx_format.check_graph`), or external
            weights outside the model's folder.
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
    check_graph(model, str(p))
    _check_external_data(model, p)
    return info


def _check_external_data(model: Any, path: Path) -> None:
    """Refuse weights stored outside the model's folder (``../``, an absolute path, a link out of it), that
    are not a regular file, or that a tensor reads past the end of.

    Raises:
        OnnxPredictorError: the tensor and its location, named.
    """
    import onnx

    folder = Path(os.path.realpath(path.parent))
    tensors = list(model.graph.initializer)
    for sparse in model.graph.sparse_initializer:
        tensors += [sparse.values, sparse.indices]
    for node in model.graph.node:
        for attr in node.attribute:
            tensors += ([attr.t] if attr.HasField("t") else []) + list(attr.tensors)
    for t in tensors:
        if t.data_location != onnx.TensorProto.EXTERNAL:
            continue
        entries = {e.key: e.value for e in t.external_data}
        location = entries.get("location", "")
        where = f"{path}: tensor {t.name!r} keeps its data in {location!r}"
        target = Path(os.path.realpath(folder / location)) if location else folder
        if not location or Path(location).is_absolute() or ".." in Path(location).parts or folder not in target.parents:
            raise OnnxPredictorError(f"{where}, outside the model's folder: refused")
        if not target.is_file():
            raise OnnxPredictorError(f"{where}, which is not a file beside it")
        try:
            offset, length = int(entries.get("offset", 0)), int(entries.get("length", 0))
        except ValueError:
            raise OnnxPredictorError(f"{where} with a malformed offset/length") from None
        if offset < 0 or length < 0 or offset + length > target.stat().st_size:
            raise OnnxPredictorError(f"{where} at bytes {offset}+{length}, past the end of that file")


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
        so.log_severity_level = ORT_LOG_SEVERITY
        if threads is not None:
            so.intra_op_num_threads = int(threads)
        if not spinning:
            so.add_session_config_entry("session.intra_op.allow_spinning", "0")
        t0 = time.perf_counter()
        logger.debug("onnxruntime loads %s", self.path.name)
        try:
            self.session = _in_worker(
                "onnxruntime-load",
                lambda: ort.InferenceSession(str(self.path), sess_options=so, providers=providers),
            )
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
        """:meth:`PairPredictor.forward` through onnxruntime: ``[B, 3, H, W]`` in [0, 1] → the output tuple (CPU).

        Raises:
            ShapeError / InputError: inputs the file does not take.
            OnnxPredictorError: the run failed (onnxruntime's message), or its outputs are not a predictor's.
            KeyboardInterrupt: Ctrl-C or SIGTERM during the run (stopped within seconds).
        """
        self._check(img0, img1)
        feeds = {
            name: np.ascontiguousarray(t.detach().to("cpu", torch.float32).numpy())
            for name, t in zip(INPUT_NAMES, (img0, img1))
        }
        outputs = self._run(feeds)
        try:
            result = tuple(torch.from_numpy(np.asarray(o, dtype=np.float32)) for o in outputs)
        except (MemoryError, ValueError, TypeError) as e:
            raise OnnxPredictorError(f"the model failed to run: its outputs are not float arrays ({e})") from None
        b, _, h, w = img0.shape
        self._check_outputs(result, int(b), int(h), int(w))
        return result

    def _run(self, feeds: dict[str, np.ndarray]) -> list[Any]:
        """``session.run`` in a worker thread (:func:`_in_worker`): an interrupt tells onnxruntime to terminate.

        Raises:
            OnnxPredictorError: onnxruntime failed (its Fail, RuntimeException, InvalidArgument, ... or an
                allocation failure), one line.
        """
        ort = _import_ort()
        options = ort.RunOptions()
        options.log_severity_level = ORT_LOG_SEVERITY

        def terminate() -> None:
            options.terminate = True

        logger.debug("onnxruntime run of %s started (%s)", self.path.name, ", ".join(
            f"{k} {list(v.shape)}" for k, v in feeds.items()))  # fmt: skip
        try:
            return _in_worker("onnxruntime-run", lambda: self.session.run(None, feeds, options), terminate)
        except Exception as e:  # MemoryError included
            if _is_ort_error(e):
                raise OnnxPredictorError(f"the model failed to run: {_ort_message(e)}") from None
            raise

    def _check_outputs(self, outputs: tuple[torch.Tensor, ...], b: int, h: int, w: int) -> None:
        """Each output's shape as the format defines it (a hostile graph can return anything)."""
        d = self.desc_dim
        expected: dict[str, tuple[int | str, ...]] = {
            "pts3d": (b, 2, h, w, 3), "conf": (b, 2, h, w), "desc": (b, 2, h, w, d), "desc_conf": (b, 2, h, w),
            "gaussians_means": (b, 2, h, w, 3), "gaussians_log_scales": (b, 2, h, w, 3),
            "gaussians_quats": (b, 2, h, w, 4), "gaussians_opacity_logits": (b, 2, h, w),
            "gaussians_sh": (b, 2, h, w, "K", 3),
        }  # fmt: skip
        if len(outputs) != len(self.output_names):
            raise OnnxPredictorError(
                f"{self.path.name} returned {len(outputs)} outputs, expected {len(self.output_names)}"
            )
        for name, t in zip(self.output_names, outputs):
            want = expected[name]
            got = tuple(t.shape)
            fits = len(got) == len(want) and all(g == x or (x == "K" and g in (1, 4, 9, 16)) for g, x in zip(got, want))
            if not fits:
                shape = ", ".join(str(x) for x in want).replace("K", "K=1|4|9|16")
                raise OnnxPredictorError(
                    f"{self.path.name}: its output {name} has shape {list(got)}, expected [{shape}]"
                )

    forward = __call__

    def predict(self, img0: torch.Tensor, img1: torch.Tensor) -> PairPrediction:
        """The outputs named, as :meth:`PairPredictor.predict`."""
        return prediction_from_outputs(self(img0, img1))

    def __repr__(self) -> str:
        return f"OnnxPairPredictor({os.fspath(self.path)!r}, providers={self.providers})"
